"""One run, spec -> build -> run -> result: the orchestration of `run`. It plans the run (`run.plan`), makes
or reuses the dataset and the encoder (`run.artifacts`), evaluates the task under the run's lock and stores
the record (`run.record`).

Identities are content hashes (`identity`): a run's id covers the resolved config (encoder spec, task
spec, preset values, overrides), preset name, seed, the dataset's fingerprint, the library versions and
the code of the encoder, the task and the runner (a plugin's distribution, version and source; the
runner's with every module it imports, `plan`, `artifacts` and `record` included); an
encoder's checkpoint key covers its resolved spec, the dataset fingerprint, the seed and the encoder's
code, so tasks that share a dataset share the trained encoder and nothing else is ever served from a cache.
`--force` computes a run again, its encoder fitted afresh in the run's own folder (the shared checkpoint
stays for the runs that load it): an equal result leaves the stored one, a different one (nondeterminism)
is stored under its own id and named as a rerun, so one id never stands for two results. A run that reads
no data (an online task and an encoder that fits nothing, `PreparedRun.reads_data`) collects none. Two
processes asked for the same run hold a lock on its id: one computes, the other then finds the result.
"""

from __future__ import annotations

import shutil
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mftcn_bench.core.device import determinism
from mftcn_bench.core.errors import BenchWarning
from mftcn_bench.core.fileio import exclusive_lock
from mftcn_bench.core.home import BenchHome
from mftcn_bench.core.provenance import warn_if_dirty
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import Encoder
from mftcn_bench.results.store import ResultStore, RunRecord
from mftcn_bench.run.artifacts import build_encoder, prepare_dataset
from mftcn_bench.run.plan import PreparedRun, RunRequest, prepare_with_encoder, run_id_of
from mftcn_bench.run.portable import PLAN, plan_of, write_plan
from mftcn_bench.run.record import build_record, placement_notes, rerun_id, same_metrics, store_record
from mftcn_bench.tasks.base import OnlineTask, ShowsProgress


@dataclass(frozen=True)
class RunOutcome:
    record: RunRecord
    reused: bool
    table: list[dict[str, Any]]
    notes: list[str]


class RerunWarning(BenchWarning):
    """`--force` gave a result that differs from the stored run of the same id."""


def run(request: RunRequest, home: BenchHome, show_progress: bool = True) -> RunOutcome:
    """Run (or reuse) one (encoder, task, preset, seed) and return its stored record; with
    `request.deterministic`, torch's deterministic algorithms hold for the run only."""
    began = time.monotonic()
    prepared, untrained = prepare_with_encoder(request)
    with determinism(prepared.placement):
        return _run(prepared, untrained, home, show_progress, began)


def _run(prepared: PreparedRun, untrained: Encoder | None, home: BenchHome, show_progress: bool,
         began: float) -> RunOutcome:
    store = ResultStore(home.database)
    store.check_writable()
    warn_if_dirty()
    dataset = prepare_dataset(prepared, home, show_progress)
    after_data = time.monotonic()
    run_id = run_id_of(prepared, None if dataset is None else dataset.fingerprint)
    # Two processes asked for one run share `runs/<id>`: the second waits here, then finds the result stored.
    with exclusive_lock(home.runs / f".{run_id}.lock"):
        return _run_once(prepared, untrained, home, show_progress, began, dataset, after_data, run_id, store)


def _run_once(prepared: PreparedRun, untrained: Encoder | None, home: BenchHome, show_progress: bool,
              began: float, dataset: MultiViewDataset | None, after_data: float, run_id: str,
              store: ResultStore) -> RunOutcome:
    request = prepared.request
    existing = store.get(run_id)
    if existing is not None and not request.force:
        return RunOutcome(existing, True, prepared.task.table(existing.metrics),
                          existing.config.get("notes", []))
    # A forced rerun computes from scratch in a folder of its own; a first run keeps its folder, so a
    # killed evaluation resumes from its checkpoints there.
    run_dir = home.runs / (f".{run_id}.rerun" if existing is not None else run_id)
    if existing is not None:
        shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        # `--force` fits the encoder again in the run's own folder: the shared checkpoint, which other tasks'
        # runs load (and may be loading now), is never removed or replaced.
        encoder, fit = build_encoder(prepared, dataset, home, show_progress,
                                     fit_dir=run_dir / "encoder" if request.force else None, untrained=untrained)
        after_fit = time.monotonic()
        if not request.force:  # what `runs export` needs to move the run to another home from here on
            shared = Path(fit["checkpoint"]).parent if "checkpoint" in fit else None
            write_plan(run_dir, plan_of(run_id, list(request.overrides), encoder=request.encoder, task=request.task,
                                        preset=prepared.preset, seed=request.seed,
                                        dataset=None if dataset is None else dataset.fingerprint,
                                        encoder_dir=None if shared is None else shared.name))
        if isinstance(prepared.task, ShowsProgress):
            prepared.task.show_progress(show_progress)
        if dataset is None and isinstance(prepared.task, OnlineTask):  # only such a run reads no data
            result = prepared.task.evaluate_online(encoder, run_dir)
        else:
            result = prepared.task.evaluate(encoder, dataset, run_dir)
    except BaseException:
        # nothing to resume from (the plan alone is no progress): leave no folder behind
        if existing is not None or not any(path.name != PLAN for path in run_dir.iterdir()):
            shutil.rmtree(run_dir, ignore_errors=True)
        raise
    done = time.monotonic()
    notes = placement_notes(prepared, fit)
    if "train" in result.curves:  # the learning curve beside the result (matplotlib only when needed)
        from mftcn_bench.results.figure import plot_run_curve

        plot_run_curve(result.curves["train"], run_dir / "curve.png", f"{request.encoder} on {request.task}")
    record_id = run_id
    if existing is not None:
        if same_metrics(existing.metrics, result.metrics):
            shutil.rmtree(run_dir, ignore_errors=True)  # reproduced: the stored record and folder stay
            return RunOutcome(existing, False, prepared.task.table(existing.metrics),
                              [*result.notes, f"--force: computed again, the same metrics as stored run {run_id}"])
        record_id = rerun_id(run_id, result.metrics)
        warnings.warn(f"--force: run {run_id} gave other metrics this time (not deterministic on this machine?); "
                      f"the stored result stays, the new one is run {record_id}", RerunWarning, stacklevel=2)
    final_dir = home.runs / record_id
    timings = {"dataset_s": after_data - began, "fit_s": after_fit - after_data,
               "evaluate_s": done - after_fit, "total_s": done - began}
    record = build_record(prepared, record_id, run_id, dataset, encoder, fit, result, [*result.notes, *notes],
                          timings, final_dir)
    store_record(record, run_dir, final_dir, store)
    return RunOutcome(record, False, prepared.task.table(result.metrics), [*result.notes, *notes])
