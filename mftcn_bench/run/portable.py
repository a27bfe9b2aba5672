"""Portable checkpoints: an unfinished run moved from one home to another, to continue there.

A long run (a pixels-cnn seed, a 160x160 row) can outlast the machine it started on. Once its encoder is
fitted the runner writes `plan.json` into the run's folder (the command, the data set's fingerprint, the
encoder folder it loads); `export_run` copies that folder (PPO's checkpoint: networks, optimiser,
observation statistics, RNG, curves, frames done) and the fitted encoder's folder to a directory small
enough to commit, and `import_run` puts them into another home. The same `mftcn-bench run` command there
finds the run's folder under the same run id and resumes from the checkpoint, to the result an
uninterrupted run gives. The run id holds the code and the data set's fingerprint: a run that reads no data
(pixels-cnn, true state) always continues; one that does continues when the new machine makes the same
data set (it says which fingerprint it needs).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.core.home import BenchHome
from mftcn_bench.rl.checkpoint_progress import checkpoint_progress

PLAN = "plan.json"          # in a run's folder, written once its encoder is ready
MANIFEST = "export.json"    # in an exported run's directory
FINISHED = "result.json"    # a finished run's record in its folder


@dataclass(frozen=True)
class RunPlan:
    """What continuing a run needs besides its folder."""

    run_id: str
    encoder: str
    task: str
    preset: str
    seed: int
    overrides: list[str]                 # KEY=VALUE, as `--set` takes them
    dataset: str | None                  # the data set's fingerprint (None: the run reads no data)
    encoder_dir: str | None              # the fitted encoder's folder under the home's encoders/

    def command(self) -> str:
        sets = "".join(f" --set {item}" for item in self.overrides)
        return (f"mftcn-bench run --encoder {self.encoder} --task {self.task} --preset {self.preset} "
                f"--seed {self.seed}{sets}")


def write_plan(run_dir: Path, plan: RunPlan) -> None:
    atomic_write_bytes(run_dir / PLAN, json.dumps(asdict(plan), indent=1).encode())


def read_plan(path: Path) -> RunPlan:
    try:
        return RunPlan(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as exc:
        raise BenchError(f"{path} is not a run plan ({type(exc).__name__}); export the run again") from None


def plan_of(run_id: str, request_overrides: list[tuple[str, Any]], **fields: Any) -> RunPlan:
    """A `RunPlan` from the runner's request (its overrides as (key, value) pairs)."""
    # JSON's literals for numbers, strings, booleans and arrays are TOML's, which `--set` parses
    return RunPlan(run_id=run_id, overrides=[f"{k}={json.dumps(v)}" for k, v in request_overrides], **fields)


@dataclass(frozen=True)
class Moved:
    """What `export_run` or `import_run` moved."""

    plan: RunPlan
    folder: Path                 # the exported directory, or the run's folder in the importing home
    progress: str                # what the checkpoint holds, in words


def _progress(run_dir: Path) -> str:
    found = checkpoint_progress(run_dir)
    return "no PPO checkpoint yet" if found is None else f"{found.frames / 1e6:.2f} M frames trained"


def export_run(home: BenchHome, run_id: str, out: Path) -> Moved:
    """Copy the unfinished run `run_id` of `home` (its folder and fitted encoder) to `out/<run_id>/`."""
    run_dir = home.runs / run_id
    if not run_dir.is_dir():
        raise BenchError(f"no run {run_id!r} in {home.runs}; `mftcn-bench sweep status` lists the running "
                         f"runs' ids")
    if (run_dir / FINISHED).exists():
        raise BenchError(f"run {run_id} is finished: export its record with `mftcn-bench results export`, "
                         f"not its checkpoint")
    if not (run_dir / PLAN).exists():
        raise BenchError(f"run {run_id} has no {PLAN}: it is still fitting its encoder (whose own checkpoint "
                         f"resumes in place) or was started by an older harness; export it once PPO has begun")
    plan = read_plan(run_dir / PLAN)
    target = out / run_id
    if target.exists():
        raise BenchError(f"{target} exists; export to another folder or remove it")
    staging = out / f".{run_id}.partial"
    shutil.rmtree(staging, ignore_errors=True)
    # Checkpoints are replaced atomically while a run goes on, so a copy taken beside it is one checkpoint.
    shutil.copytree(run_dir, staging / "run", ignore=shutil.ignore_patterns(".*"))
    if plan.encoder_dir is not None:
        shutil.copytree(home.encoders / plan.encoder_dir, staging / "encoder" / plan.encoder_dir,
                        ignore=shutil.ignore_patterns(".*", "train_checkpoint.pt"))
    progress = _progress(staging / "run")
    atomic_write_bytes(staging / MANIFEST, json.dumps({**asdict(plan), "progress": progress}, indent=1).encode())
    staging.rename(target)  # an export cut off by a kill is never taken for a whole one
    return Moved(plan, target, progress)


def import_run(home: BenchHome, folder: Path) -> Moved:
    """Put an exported run (`export_run`'s directory) into `home`, to continue with `plan.command()`."""
    if not (folder / MANIFEST).exists():
        raise BenchError(f"{folder} is not an exported run (no {MANIFEST}); `mftcn-bench runs export RUN_ID DIR` "
                         f"writes one")
    plan = read_plan(folder / "run" / PLAN)
    run_dir = home.runs / plan.run_id
    if run_dir.exists():
        raise BenchError(f"run {plan.run_id} is already in {home.runs}; remove that folder first to replace it")
    if plan.encoder_dir is not None:
        source, target = folder / "encoder" / plan.encoder_dir, home.encoders / plan.encoder_dir
        if not target.exists():
            staging = home.encoders / f".{plan.encoder_dir}.import"
            shutil.rmtree(staging, ignore_errors=True)
            shutil.copytree(source, staging)
            staging.rename(target)
        elif (target / "fit.json").read_bytes() != (source / "fit.json").read_bytes():
            raise BenchError(f"{target} holds another fit of this encoder key than the exported one; the run "
                             f"would not continue with its own encoder")
    staging = home.runs / f".{plan.run_id}.import"
    shutil.rmtree(staging, ignore_errors=True)
    home.runs.mkdir(parents=True, exist_ok=True)
    shutil.copytree(folder / "run", staging)
    staging.rename(run_dir)
    return Moved(plan, run_dir, _progress(run_dir))
