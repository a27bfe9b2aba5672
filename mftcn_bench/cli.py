"""The `mftcn-bench` command line: run, list, data, report.

Bad input ends with one line on stderr naming what was wrong and what is allowed, and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence
from typing import Any, NoReturn

from tabulate import tabulate

from mftcn_bench.errors import BenchError, SpecError
from mftcn_bench.home import ENV_VAR, BenchHome
from mftcn_bench.specs import parse_override

DEFAULT_ENCODER = "mftcn4"
DEFAULT_TASK = "cartpole-probe"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise SpecError(f"{self.prog}: {message}")


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4f}"
    return str(value)


def _print_table(rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    body = [[_fmt(row.get(column)) for column in rows[0]] for row in rows]
    print(tabulate(body, headers=list(rows[0]), tablefmt="github", disable_numparse=True))


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise SpecError(f"--seed must be a non-negative integer, got {text!r}") from None
    if value < 0:
        raise SpecError(f"--seed must be a non-negative integer, got {value}")
    return value


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--home", help=f"folder for datasets, encoders and results (default ${ENV_VAR} "
                                       "or ~/.mftcn-bench)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mftcn-bench", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    run = commands.add_parser("run", help="run one encoder on one task and print its result")
    run.add_argument("--encoder", default=DEFAULT_ENCODER, help=f"encoder name (default {DEFAULT_ENCODER})")
    run.add_argument("--task", default=DEFAULT_TASK, help=f"task name (default {DEFAULT_TASK})")
    run.add_argument("--preset", help="task preset: smoke, quick or paper (default: the task's own)")
    run.add_argument("--seed", type=_seed, default=0)
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a spec value, e.g. encoder.embedding_dim=8 (repeatable)")
    run.add_argument("--force", action="store_true", help="recompute even if a stored result exists")
    _common(run)

    listing = commands.add_parser("list", help="list registered encoders or tasks")
    listing.add_argument("kind", choices=["encoders", "tasks"])

    data = commands.add_parser("data", help="datasets")
    data_commands = data.add_subparsers(dest="data_command", required=True, parser_class=_Parser)
    collect = data_commands.add_parser("collect", help="collect the dataset a task needs")
    collect.add_argument("task", help="task whose dataset to collect, e.g. cartpole-probe")
    collect.add_argument("--preset")
    collect.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    _common(collect)

    report = commands.add_parser("report", help="print a paper table from stored results")
    report.add_argument("table", choices=["probe"])
    report.add_argument("--preset", help="only results of this preset")
    _common(report)
    return parser


def cmd_run(args: argparse.Namespace) -> None:
    from mftcn_bench.runner import RunRequest, run

    request = RunRequest(args.encoder, args.task, args.preset, args.seed,
                         tuple(parse_override(o) for o in args.overrides), args.force)
    outcome = run(request, BenchHome.resolve(args.home), show_progress=not args.no_progress)
    record = outcome.record
    how = "reused stored result" if outcome.reused else f"finished in {record.timings['total_s']:.1f} s"
    print(f"{record.encoder} on {record.task} (preset {record.preset}, seed {record.seed}): {how}; "
          f"run {record.run_id}")
    _print_table(outcome.table)
    for note in outcome.notes:
        print(note)


def cmd_list(args: argparse.Namespace) -> None:
    from mftcn_bench import registry

    _print_table(registry.describe(args.kind))


def cmd_data(args: argparse.Namespace) -> None:
    from mftcn_bench.runner import RunRequest, prepare, prepare_dataset

    overrides = tuple(parse_override(o) for o in args.overrides)
    prepared = prepare(RunRequest(DEFAULT_ENCODER, args.task, args.preset, 0, overrides))
    dataset = prepare_dataset(prepared, BenchHome.resolve(args.home), show_progress=not args.no_progress)
    frames = sum(dataset.episode_length(i) for s in ("train", "test") for i in dataset.episodes(s))
    train, test = len(dataset.episodes("train")), len(dataset.episodes("test"))
    print(f"dataset {dataset.config['name']} ({dataset.dataset_id}): {train} train + {test} test episodes, "
          f"{frames} frames x {len(dataset.cameras)} views "
          f"at {dataset.image_shape[1]}x{dataset.image_shape[0]}, in {dataset.root}")


def cmd_report(args: argparse.Namespace) -> None:
    from mftcn_bench.report import PROBE_COLUMNS, probe_table
    from mftcn_bench.store import ResultStore

    table = probe_table(ResultStore(BenchHome.resolve(args.home).database), args.preset)
    if table.empty:
        print("no mfTCN cartpole-probe results stored yet; run e.g. "
              "`mftcn-bench run --encoder mftcn4 --task cartpole-probe`")
        return
    rows = []
    for row in table.to_dict("records"):
        out = {k: row[k] for k in ("preset", "embedding", "lookback", "seeds")}
        for column in PROBE_COLUMNS:
            paper = row[f"{column} (paper)"]
            out[column.removeprefix("mse_")] = _fmt(row[column]) + (f" ({paper:.4f})" if paper else "")
        rows.append(out)
    print("Cartpole state regression MSE: ours (paper), mean over seeds of runs made with the current spec files "
          "(embedding size by override). Paper figures are at paper scale (160k/20k frames).")
    _print_table(rows)


COMMANDS = {"run": cmd_run, "list": cmd_list, "data": cmd_data, "report": cmd_report}


_show_warning = warnings.showwarning


def _warn_one_line(message, category, filename, lineno, file=None, line=None) -> None:
    """Plugin problems as one line; other warnings as Python shows them."""
    from mftcn_bench.registry import PluginWarning

    if issubclass(category, PluginWarning):
        print(f"mftcn-bench: warning: {message}", file=sys.stderr)
    else:
        _show_warning(message, category, filename, lineno, file, line)


def main(argv: Sequence[str] | None = None) -> int:
    warnings.showwarning = _warn_one_line
    try:
        args = build_parser().parse_args(argv)
        COMMANDS[args.command](args)
    except BenchError as exc:
        print(f"mftcn-bench: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("mftcn-bench: interrupted; finished work is kept and a rerun continues from it",
              file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
