"""The record of a finished run (`RunRecord`): built from the plan, the encoder's fit and the task's result,
and stored with the run's folder, so that a result is in the store with its folder or nowhere.

A forced rerun whose metrics differ from the stored run's is recorded under an id of its own (`rerun_id`),
so one id never stands for two results.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.core.provenance import canonical_json, content_hash, versions
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import FIT_CURVE, Encoder
from mftcn_bench.encoders.privileged import declared_inputs
from mftcn_bench.results.store import ResultStore, RunRecord
from mftcn_bench.run.plan import PreparedRun
from mftcn_bench.tasks.base import TaskResult


def fit_curve(fit: Mapping[str, Any]) -> dict[str, list[float]] | None:
    """The learning curve the fit behind `fit` (`run.artifacts.build_encoder`'s record of it) wrote, if any."""
    if "checkpoint" not in fit:
        return None
    path = Path(fit["checkpoint"]).parent / FIT_CURVE
    return json.loads(path.read_text()) if path.exists() else None


def same_metrics(stored: Mapping[str, Any], computed: Mapping[str, Any]) -> bool:
    """Whether a rerun reproduced the stored metrics (compared as the store writes them)."""
    return canonical_json(stored) == canonical_json(computed)


def rerun_id(run_id: str, metrics: Mapping[str, Any]) -> str:
    """The id of a forced rerun of `run_id` that gave `metrics`, other than the stored run's."""
    return content_hash({"rerun_of": run_id, "metrics": metrics})


def placement_notes(prepared: PreparedRun, fit: Mapping[str, Any]) -> list[str]:
    """A note when the encoder computed elsewhere than the run (it cannot move off the CPU)."""
    if fit["device"] == prepared.placement.device:
        return []
    return [f"encoder {prepared.request.encoder!r} has no to_device: it ran on the CPU, the task on "
            f"{prepared.placement.device}"]


def build_record(prepared: PreparedRun, record_id: str, run_id: str, dataset: MultiViewDataset | None,
                 encoder: Encoder, fit: Mapping[str, Any], result: TaskResult, notes: list[str],
                 timings: dict[str, float], final_dir: Path) -> RunRecord:
    """The record of run `run_id` stored as `record_id` (another id for a rerun that gave other metrics) in
    `final_dir`; read before the run's folder moves there (a forced fit's curve is read where it was made)."""
    request = prepared.request
    curves = result.curves
    if (fitted := fit_curve(fit)) is not None:
        curves = {**curves, "fit": fitted}
    if "checkpoint" in fit and request.force:  # the forced fit moves with the run's folder
        fit = {**fit, "checkpoint": str(final_dir / "encoder" / Path(fit["checkpoint"]).name)}
    return RunRecord(
        run_id=record_id, encoder=request.encoder, task=request.task, preset=prepared.preset,
        seed=request.seed, dataset_id=None if dataset is None else dataset.fingerprint,
        config={**prepared.config, "preset": prepared.preset, "seed": request.seed,
                "encoder_info": asdict(encoder.info), "privileged": list(declared_inputs(encoder)),
                "code": prepared.code.as_dict(), "fit": dict(fit), "notes": notes,
                "dataset_path": None if dataset is None else str(dataset.root),
                "device": prepared.placement.record(),
                **({"rerun_of": run_id} if record_id != run_id else {})},
        versions=versions(), metrics=result.metrics, timings=timings,
        artifacts=str(final_dir),
        created_at=datetime.now(UTC).isoformat(timespec="seconds"),
        curves=curves,
    )


def store_record(record: RunRecord, run_dir: Path, final_dir: Path, store: ResultStore) -> None:
    """Write `record` beside the run's artifacts in `run_dir`, move them to `final_dir` and put the record in
    the store; on any failure neither the folder nor the record stays."""
    try:
        atomic_write_bytes(run_dir / "result.json", json.dumps(asdict(record), indent=1, sort_keys=True).encode())
        if run_dir != final_dir:
            shutil.rmtree(final_dir, ignore_errors=True)  # a rerun of this same result, killed before storing
            run_dir.rename(final_dir)
        store.put(record)
    except BaseException:
        for folder in {run_dir, final_dir}:  # a result is in the store with its folder, or nowhere
            shutil.rmtree(folder, ignore_errors=True)
        raise
