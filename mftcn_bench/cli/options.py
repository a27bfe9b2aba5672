"""What the command modules share: the parser that turns usage errors into one-line exit-2 errors, the
options several commands take, the seed argument and the table printer."""

from __future__ import annotations

import argparse
from typing import Any, NoReturn

from tabulate import tabulate

from mftcn_bench.core.device import CHOICES
from mftcn_bench.core.device import ENV_VAR as DEVICE_ENV_VAR
from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.home import ENV_VAR


class Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise SpecError(f"{self.prog}: {message}")


def fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4f}"
    return str(value)


def print_table(rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    body = [[fmt(row.get(column)) for column in rows[0]] for row in rows]
    print(tabulate(body, headers=list(rows[0]), tablefmt="github", disable_numparse=True))


def seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise SpecError(f"--seed must be a non-negative integer, got {text!r}") from None
    if value < 0:
        raise SpecError(f"--seed must be a non-negative integer, got {value}")
    return value


def add_device_options(parser: argparse.ArgumentParser) -> None:
    """--device and --deterministic (run, sweep, bench)."""
    parser.add_argument("--device", help=f"where networks compute: {CHOICES} (default ${DEVICE_ENV_VAR} or "
                                         "auto: CUDA when torch sees a GPU)")
    parser.add_argument("--deterministic", action="store_true",
                        help="torch's deterministic algorithms (slower on a GPU; see README, determinism)")


def common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--home", help=f"folder for datasets, encoders and results (default ${ENV_VAR} "
                                       "or ~/.mftcn-bench)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
