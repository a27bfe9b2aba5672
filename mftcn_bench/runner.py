"""One run, spec -> build -> run -> result: resolve the config, make or reuse the dataset, fit or reuse the
encoder, evaluate the task, store the result.

Identities are content hashes: a run's id covers the resolved config (encoder spec, task spec, preset
values, overrides), preset name, seed, the dataset's fingerprint and the package version; an encoder's
checkpoint key covers its resolved spec, the dataset fingerprint, the seed and the package version, so
tasks that share a dataset share the trained encoder and nothing else is ever served from a cache.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import mftcn_bench
from mftcn_bench import registry
from mftcn_bench.data.dataset import MultiViewDataset, check_dataset_config, ensure_dataset
from mftcn_bench.encoders.base import Encoder, FeatureCacheUser, FitBudget
from mftcn_bench.encoders.bases import FrozenBase
from mftcn_bench.encoders.feature_cache import ensure_feature_cache
from mftcn_bench.errors import BenchError, SpecError
from mftcn_bench.fileio import atomic_write_bytes, exclusive_lock
from mftcn_bench.home import BenchHome
from mftcn_bench.provenance import content_hash, versions
from mftcn_bench.specs import EncoderSpec, encoder_spec_from_config, resolve_config
from mftcn_bench.store import ResultStore, RunRecord
from mftcn_bench.tasks.base import Task


@dataclass(frozen=True)
class RunRequest:
    """What `mftcn-bench run` was asked for."""

    encoder: str
    task: str
    preset: str | None = None
    seed: int = 0
    overrides: Sequence[tuple[str, Any]] = field(default_factory=tuple)
    force: bool = False


@dataclass(frozen=True)
class RunOutcome:
    record: RunRecord
    reused: bool
    table: list[dict[str, Any]]
    notes: list[str]


@dataclass(frozen=True)
class PreparedRun:
    """A request resolved against the registry and specs, with its task built."""

    request: RunRequest
    preset: str
    config: dict[str, Any]
    encoder_entry: registry.Entry
    task: Task


def prepare(request: RunRequest) -> PreparedRun:
    """Resolve names, preset and overrides; build the task. Fails fast on bad input, before any work."""
    if request.seed < 0:
        raise BenchError(f"seed must be a non-negative integer, got {request.seed}")
    encoder_entry = registry.get("encoders", request.encoder)
    task_entry = registry.get("tasks", request.task)
    preset, config = resolve_config(encoder_entry.spec, task_entry.spec, request.preset, request.overrides)
    spec = encoder_spec_from_config(encoder_entry.description, config["encoder"])  # validates overrides
    encoder_entry.load()  # a plugin that fails to import fails here, before any work
    task = task_entry.load()(config["task"], request.seed)
    dataset_config = getattr(task, "dataset_config", None)
    if isinstance(dataset_config, Mapping):  # sizes that cannot work are refused before collecting anything
        check_dataset_config(dataset_config)
        length = dataset_config.get("episode_length")
        if isinstance(length, int) and spec.lookback > length:
            raise SpecError(f"encoder {spec.name!r} has a lookback of {spec.lookback} frames ({spec.frames} at "
                            f"stride {spec.stride}), longer than the task's {length}-frame episodes; use an "
                            f"encoder with lookback <= {length} or set task.dataset.episode_length >= "
                            f"{spec.lookback}")
    return PreparedRun(request, preset, config, encoder_entry, task)


def prepare_dataset(prepared: PreparedRun, home: BenchHome, show_progress: bool = True) -> MultiViewDataset:
    """The task's dataset, after whatever the task needs to collect it (an expert policy for demos)."""
    prepare_artifacts = getattr(prepared.task, "prepare_artifacts", None)
    if prepare_artifacts is not None:
        prepare_artifacts(home, show_progress)
    return ensure_dataset(home.datasets, prepared.task.dataset_config, prepared.task.collector,
                          show_progress=show_progress)


def _progress_bar(name: str, enabled: bool):
    from tqdm import tqdm

    bar = tqdm(desc=f"fit {name}", unit="step", disable=not enabled, leave=False)

    def report(step: int, total: int, stats: dict[str, float]) -> None:
        bar.total = total
        bar.n = step
        bar.set_postfix({k: f"{v:.4f}" for k, v in stats.items()}, refresh=False)
        bar.refresh()

    return bar, report


def encoder_workdir(prepared: PreparedRun, dataset: MultiViewDataset, home: BenchHome,
                    base_identity: Mapping[str, Any] | None = None) -> Path:
    """The folder of the encoder this run fits or reuses: keyed by its resolved spec, the dataset's
    fingerprint, the seed, the package version and, for a frozen base, the base's identity (its weights'
    checksum)."""
    config = prepared.config["encoder"]
    keyed: dict[str, Any] = {"encoder": config, "dataset": dataset.fingerprint, "seed": prepared.request.seed,
                             "version": mftcn_bench.__version__}
    if base_identity is not None:
        keyed["base"] = dict(base_identity)
    return home.encoders / f"{config['name']}-{content_hash(keyed)}"


def frozen_base_of(encoder: Encoder) -> FrozenBase | None:
    """The encoder's frozen base when it declares one (the `FeatureCacheUser` capability)."""
    return encoder.frozen_base() if isinstance(encoder, FeatureCacheUser) else None


def attach_feature_cache(encoder: Encoder, dataset: MultiViewDataset, home: BenchHome,
                         show_progress: bool = True) -> dict[str, Any] | None:
    """Build (or find) the per-frame feature cache of the encoder's frozen base on `dataset` and hand it to
    the encoder; returns what the run records about it (None: the encoder has no frozen base)."""
    base = frozen_base_of(encoder)
    if base is None or not isinstance(encoder, FeatureCacheUser):
        return None
    cache = ensure_feature_cache(home.features, dataset, base, base.identity(), show_progress=show_progress)
    encoder.use_feature_cache(cache)
    return {**cache.summary(), "base": base.identity()}


def build_encoder(prepared: PreparedRun, dataset: MultiViewDataset, home: BenchHome,
                  show_progress: bool = True) -> tuple[Encoder, dict[str, Any]]:
    """The encoder for this run, fitted on `dataset` or loaded from the shared checkpoint."""
    config, seed = prepared.config, prepared.request.seed
    spec = encoder_spec_from_config(prepared.encoder_entry.description, config["encoder"])
    encoder = prepared.encoder_entry.load()(spec, image_shape=dataset.image_shape, seed=seed)
    if not isinstance(encoder, Encoder):
        raise BenchError(f"encoder {spec.name!r} ({prepared.encoder_entry.entry_point.value}) does not "
                         f"implement the Encoder protocol (info, needs_fit, fit, embed, save, load)")
    base = frozen_base_of(encoder)
    if not encoder.needs_fit:
        cache = attach_feature_cache(encoder, dataset, home, show_progress)
        return encoder, {"fitted": False, "reused": False, **({} if cache is None else {"feature_cache": cache})}
    workdir = encoder_workdir(prepared, dataset, home, None if base is None else base.identity())
    with exclusive_lock(home.encoders / f".{workdir.name}.lock"):  # concurrent runs fit it once
        # A stored checkpoint is loaded (and refused if it cannot be) before the cache is built.
        fit = _fit_or_load(encoder, spec, dataset, workdir, prepared.request.force, show_progress,
                           before_fit=lambda: attach_feature_cache(encoder, dataset, home, show_progress))
    cache = attach_feature_cache(encoder, dataset, home, show_progress)  # found, if the fit built it
    return encoder, {**fit, **({} if cache is None else {"feature_cache": cache})}


def _fit_or_load(encoder: Encoder, spec: EncoderSpec, dataset: MultiViewDataset, workdir: Path, force: bool,
                 show_progress: bool, before_fit: Callable[[], object] = lambda: None) -> dict[str, Any]:
    """Load the checkpoint in `workdir`, or fit (resuming a killed fit, after `before_fit`) and save it."""
    model_path = workdir / "model.pt"
    if force and workdir.exists():
        shutil.rmtree(workdir)
    if model_path.exists():
        encoder.load(model_path)
        fit_file = workdir / "fit.json"
        trained = json.loads(fit_file.read_text()) if fit_file.exists() else {}
        return {"fitted": False, **trained, "reused": True, "checkpoint": str(model_path)}
    workdir.mkdir(parents=True, exist_ok=True)
    for stale in workdir.glob(".*.tmp-*"):  # a checkpoint write cut off by a kill (we hold the lock): never read
        stale.unlink()
    before_fit()
    train = dict(spec.train)
    budget = FitBudget(steps=int(train.get("steps", 0)), max_seconds=train.get("max_seconds") or None)
    bar, report = _progress_bar(spec.name, show_progress)
    try:
        fit_stats = encoder.fit(dataset, budget, report, workdir)
    except BaseException:
        if not any(workdir.iterdir()):  # nothing to resume from: leave no empty folder behind
            workdir.rmdir()
        raise
    finally:
        bar.close()
    encoder.save(model_path)
    (workdir / "train_checkpoint.pt").unlink(missing_ok=True)
    atomic_write_bytes(workdir / "fit.json", json.dumps(fit_stats, indent=1).encode())
    return {"fitted": True, "reused": False, "checkpoint": str(model_path), **fit_stats}


def run(request: RunRequest, home: BenchHome, show_progress: bool = True) -> RunOutcome:
    """Run (or reuse) one (encoder, task, preset, seed) and return its stored record."""
    began = time.monotonic()
    prepared = prepare(request)
    store = ResultStore(home.database)
    store.check_writable()
    dataset = prepare_dataset(prepared, home, show_progress)
    after_data = time.monotonic()
    run_id = content_hash({"config": prepared.config, "preset": prepared.preset, "seed": request.seed,
                           "dataset": dataset.fingerprint, "version": mftcn_bench.__version__})
    existing = store.get(run_id)
    if existing is not None and not request.force:
        return RunOutcome(existing, True, prepared.task.table(existing.metrics),
                          existing.config.get("notes", []))
    encoder, fit = build_encoder(prepared, dataset, home, show_progress)
    after_fit = time.monotonic()
    run_dir = home.runs / run_id
    run_dir.mkdir(parents=True, exist_ok=True)
    try:
        result = prepared.task.evaluate(encoder, dataset, run_dir)
    except BaseException:
        if not any(run_dir.iterdir()):  # nothing to resume from: leave no empty run folder behind
            run_dir.rmdir()
        raise
    done = time.monotonic()
    record = RunRecord(
        run_id=run_id, encoder=request.encoder, task=request.task, preset=prepared.preset,
        seed=request.seed, dataset_id=dataset.fingerprint,
        config={**prepared.config, "preset": prepared.preset, "seed": request.seed,
                "encoder_info": asdict(encoder.info), "fit": fit, "notes": result.notes,
                "dataset_path": str(dataset.root)},
        versions=versions(), metrics=result.metrics,
        timings={"dataset_s": after_data - began, "fit_s": after_fit - after_data,
                 "evaluate_s": done - after_fit, "total_s": done - began},
        artifacts=str(home.runs / run_id),
        curves=result.curves,
    )
    try:
        atomic_write_bytes(run_dir / "result.json", json.dumps(asdict(record), indent=1, sort_keys=True).encode())
        store.put(record)
    except BaseException:
        shutil.rmtree(run_dir, ignore_errors=True)  # a result is in the store with its folder, or nowhere
        raise
    return RunOutcome(record, False, prepared.task.table(result.metrics), result.notes)
