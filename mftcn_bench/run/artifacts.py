"""What a run is computed from, made or found again: the task's dataset, the encoder (constructed, placed on
the run's device, fitted or loaded from its shared checkpoint) and its frozen base's feature cache.

A trained encoder is shared by every run of its key (`run.plan.encoder_key_of`) under `encoders/`, fitted
once under a lock; `--force` fits it afresh in a folder of the run's own and leaves the shared one alone.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mftcn_bench.core.device import CPU, DevicePlaced, Placement
from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.fileio import atomic_write_bytes, exclusive_lock
from mftcn_bench.core.home import BenchHome
from mftcn_bench.core.progress import progress_bar
from mftcn_bench.core.specs import EncoderSpec, encoder_spec_from_config
from mftcn_bench.data.dataset import MultiViewDataset, ensure_dataset
from mftcn_bench.encoders.base import Encoder, FeatureCacheUser, fit_budget
from mftcn_bench.encoders.feature_cache import ensure_feature_cache
from mftcn_bench.encoders.privileged import dataset_for
from mftcn_bench.run.construct import construct_encoder, frozen_base_of
from mftcn_bench.run.plan import PreparedRun, encoder_key_of
from mftcn_bench.tasks.base import NeedsArtifacts


def prepare_dataset(prepared: PreparedRun, home: BenchHome, show_progress: bool = True) -> MultiViewDataset | None:
    """The task's dataset, after whatever the task needs to collect it (an expert policy for demos); None,
    with nothing collected, for a run that reads no data (`PreparedRun.reads_data`)."""
    if not prepared.reads_data:
        return None
    if isinstance(prepared.task, NeedsArtifacts):
        prepared.task.prepare_artifacts(home, show_progress)
    return ensure_dataset(home.datasets, prepared.task.dataset_config, prepared.task.collector,
                          show_progress=show_progress)


def encoder_workdir(prepared: PreparedRun, dataset: MultiViewDataset, home: BenchHome,
                    placement: Placement | None = None) -> Path:
    """The folder of the encoder this run fits or reuses (`encoder_key_of`; for a frozen base the key also
    holds the base's identity, its weights' checksum)."""
    key = encoder_key_of(prepared, dataset.fingerprint, placement)
    return home.encoders / f"{prepared.config['encoder']['name']}-{key}"


def attach_feature_cache(encoder: Encoder, dataset: MultiViewDataset, home: BenchHome,
                         show_progress: bool = True, placement: Placement = CPU) -> dict[str, Any] | None:
    """Build (or find) the per-frame feature cache of the encoder's frozen base on `dataset` (the base runs
    where the encoder was placed) and hand it to the encoder; returns what the run records about it (None:
    the encoder has no frozen base)."""
    base = frozen_base_of(encoder)
    if base is None or not isinstance(encoder, FeatureCacheUser):
        return None
    cache = ensure_feature_cache(home.features, dataset, base, base.identity(), show_progress=show_progress,
                                 placement=placement)
    encoder.use_feature_cache(cache)
    return {**cache.summary(), "base": base.identity()}


def place_encoder(encoder: Encoder, placement: Placement) -> Placement:
    """Move the encoder to the run's device when it can (`DevicePlaced`); returns where it computes: an
    encoder without `to_device` stays on the CPU."""
    if isinstance(encoder, DevicePlaced):
        encoder.to_device(placement.torch_device)
        return placement
    return CPU


def build_encoder(prepared: PreparedRun, dataset: MultiViewDataset | None, home: BenchHome,
                  show_progress: bool = True, fit_dir: Path | None = None,
                  untrained: Encoder | None = None) -> tuple[Encoder, dict[str, Any]]:
    """The encoder for this run, placed on the run's device, fitted on `dataset` or loaded from the shared
    checkpoint (with no dataset, a run that reads no data: the encoder as constructed). With `fit_dir` (a
    folder of the caller's own, `--force`) the fit happens there and the shared checkpoint is left alone.
    `untrained` is the encoder `prepare_with_encoder` constructed for this plan, used (and changed: placed,
    fitted) here instead of constructing another; hand it to one call only. Without it, one is constructed."""
    spec = encoder_spec_from_config(prepared.encoder_entry.description, prepared.config["encoder"])
    encoder = untrained
    if encoder is None:
        shape = dataset.image_shape if dataset is not None else (prepared.task.dataset_config["height"],
                                                                 prepared.task.dataset_config["width"])
        encoder = construct_encoder(prepared.encoder_entry, prepared.config["encoder"], prepared.request.seed,
                                    shape)
    placement = place_encoder(encoder, prepared.placement)
    placed = {"device": placement.device}
    base = frozen_base_of(encoder)
    if prepared.base is not None and (base is None or base.identity() != prepared.base):  # the id holds it
        raise BenchError(f"encoder {spec.name!r}: its base's weights changed on disk since the run was "
                         f"prepared; run it again")

    if dataset is None:
        if encoder.needs_fit:
            raise BenchError(f"encoder {spec.name!r} needs a fit, and this run was planned without data")
        return encoder, {"fitted": False, "reused": False, **placed}

    def attach() -> dict[str, Any] | None:
        return attach_feature_cache(encoder, dataset, home, show_progress, placement)

    if not encoder.needs_fit:
        cache = attach()
        return encoder, {"fitted": False, "reused": False, **placed,
                         **({} if cache is None else {"feature_cache": cache})}
    if fit_dir is not None:
        fit = _fit_or_load(encoder, spec, dataset, fit_dir, show_progress, before_fit=attach)
    else:
        workdir = encoder_workdir(prepared, dataset, home, placement)
        with exclusive_lock(home.encoders / f".{workdir.name}.lock"):  # concurrent runs fit it once
            # A stored checkpoint is loaded (and refused if it cannot be) before the cache is built.
            fit = _fit_or_load(encoder, spec, dataset, workdir, show_progress, before_fit=attach)
    cache = attach()  # found, if the fit built it
    return encoder, {**fit, **placed, **({} if cache is None else {"feature_cache": cache})}


def _fit_or_load(encoder: Encoder, spec: EncoderSpec, dataset: MultiViewDataset, workdir: Path,
                 show_progress: bool, before_fit: Callable[[], object] = lambda: None) -> dict[str, Any]:
    """Load the checkpoint in `workdir`, or fit (resuming a killed fit, after `before_fit`) and save it.

    A fit is finished when `fit.json` exists: it is written atomically after `save` returned, so a save cut
    off by a kill (a plugin's `save` need not be atomic) is never taken for a finished checkpoint."""
    model_path, fit_file = workdir / "model.pt", workdir / "fit.json"
    if fit_file.exists():
        encoder.load(model_path)
        trained = json.loads(fit_file.read_text())
        return {"fitted": False, **trained, "reused": True, "checkpoint": str(model_path)}
    workdir.mkdir(parents=True, exist_ok=True)
    for stale in workdir.glob(".*.tmp-*"):  # a checkpoint write cut off by a kill (we hold the lock): never read
        stale.unlink()
    before_fit()
    budget = fit_budget(spec.name, spec.train)
    try:
        with progress_bar(f"fit {spec.name}", "step", show_progress) as report:
            fit_stats = encoder.fit(dataset_for(encoder, dataset), budget, report, workdir)
    except BaseException:
        if not any(workdir.iterdir()):  # nothing to resume from: leave no empty folder behind
            workdir.rmdir()
        raise
    encoder.save(model_path)
    atomic_write_bytes(fit_file, json.dumps(fit_stats, indent=1).encode())
    (workdir / "train_checkpoint.pt").unlink(missing_ok=True)
    return {"fitted": True, "reused": False, "checkpoint": str(model_path), **fit_stats}

