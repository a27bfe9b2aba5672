"""Where the harness keeps datasets, trained encoders, run artifacts and the results database."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mftcn_bench.core.errors import BenchError

ENV_VAR = "MFTCN_BENCH_HOME"
DEFAULT_HOME = Path("~/.mftcn-bench")


@dataclass(frozen=True)
class BenchHome:
    """The folder layout under one home: `datasets/`, `features/`, `encoders/`, `experts/`, `runs/`,
    `results.sqlite`."""

    root: Path

    @classmethod
    def resolve(cls, root: str | Path | None = None) -> BenchHome:
        """`root`, else $MFTCN_BENCH_HOME, else ~/.mftcn-bench; created if missing, must be writable."""
        path = Path(root or os.environ.get(ENV_VAR) or DEFAULT_HOME).expanduser().resolve()
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise BenchError(f"results folder {path} cannot be created ({exc.strerror}); "
                             f"choose a writable one with --home or ${ENV_VAR}") from None
        if not os.access(path, os.W_OK):
            raise BenchError(f"results folder {path} is not writable; choose a writable one with "
                             f"--home or ${ENV_VAR}")
        return cls(path)

    @property
    def datasets(self) -> Path:
        return self.root / "datasets"

    @property
    def encoders(self) -> Path:
        return self.root / "encoders"

    @property
    def features(self) -> Path:
        """Per-frame feature caches of frozen bases (`encoders/feature_cache.py`)."""
        return self.root / "features"

    @property
    def experts(self) -> Path:
        """Expert policies that demonstration datasets are recorded from."""
        return self.root / "experts"

    @property
    def runs(self) -> Path:
        return self.root / "runs"

    @property
    def database(self) -> Path:
        return self.root / "results.sqlite"
