"""One run, spec -> build -> run -> result: resolve the config, make or reuse the dataset, fit or reuse the
encoder, evaluate the task, store the result.

Identities are content hashes (`identity`): a run's id covers the resolved config (encoder spec, task
spec, preset values, overrides), preset name, seed, the dataset's fingerprint, the library versions and
the code of the encoder, the task and the runner (a plugin's distribution, version and source); an
encoder's checkpoint key covers its resolved spec, the dataset fingerprint, the seed and the encoder's
code, so tasks that share a dataset share the trained encoder and nothing else is ever served from a cache.
`--force` computes a run again, its encoder fitted afresh in the run's own folder (the shared checkpoint
stays for the runs that load it): an equal result leaves the stored one, a different one (nondeterminism)
is stored under its own id and named as a rerun, so one id never stands for two results. A run that reads
no data (an online task and an encoder that fits nothing, `PreparedRun.reads_data`) collects none. Two
processes asked for the same run hold a lock on its id: one computes, the other then finds the result.
"""

from __future__ import annotations

import json
import shutil
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from mftcn_bench.core import identity, registry
from mftcn_bench.core.device import CPU, DevicePlaced, Placement, determinism, resolve_device
from mftcn_bench.core.errors import BenchError, BenchWarning, SpecError
from mftcn_bench.core.fileio import atomic_write_bytes, exclusive_lock
from mftcn_bench.core.home import BenchHome
from mftcn_bench.core.provenance import canonical_json, content_hash, versions, warn_if_dirty
from mftcn_bench.core.specs import EncoderSpec, encoder_spec_from_config, resolve_config
from mftcn_bench.data.dataset import MultiViewDataset, check_dataset_config, dataset_id, ensure_dataset
from mftcn_bench.encoders.base import FIT_CURVE, Encoder, FeatureCacheUser, MultiViewTrainer, fit_budget
from mftcn_bench.encoders.bases import FrozenBase
from mftcn_bench.encoders.feature_cache import ensure_feature_cache
from mftcn_bench.encoders.privileged import dataset_for, declared_inputs
from mftcn_bench.results.store import ResultStore, RunRecord
from mftcn_bench.run.portable import PLAN, plan_of, write_plan
from mftcn_bench.sim.rendering import follow_device
from mftcn_bench.tasks.base import ChecksEncoder, NeedsArtifacts, OnlineTask, ShowsProgress, Task


@dataclass(frozen=True)
class RunRequest:
    """What `mftcn-bench run` was asked for."""

    encoder: str
    task: str
    preset: str | None = None
    seed: int = 0
    overrides: Sequence[tuple[str, Any]] = field(default_factory=tuple)
    force: bool = False
    device: str = "auto"          # auto, cpu, cuda or cuda:N (`core.device`)
    deterministic: bool = False   # torch's deterministic algorithms during the run (`core.device.determinism`)


@dataclass(frozen=True)
class RunOutcome:
    record: RunRecord
    reused: bool
    table: list[dict[str, Any]]
    notes: list[str]


@dataclass(frozen=True)
class PreparedRun:
    """The plan of one run: the request resolved against the registry and specs, its task built, and what
    the run will need (a dataset or none, a fit or none), learnt from the untrained encoder built once here.
    `run` and the sweep's phases (`orchestration.sweep`) both work from it."""

    request: RunRequest
    preset: str
    config: dict[str, Any]
    encoder_entry: registry.Entry
    task: Task
    code: identity.RunCode
    needs_fit: bool = True  # asked of the untrained encoder built in `prepare` (True when none was built)
    placement: Placement = CPU  # the device the run computes on, resolved in `prepare`
    base: Mapping[str, Any] | None = None  # that encoder's frozen base, weights' checksum included (None: no
    # frozen base, or a task that names no frame size, so no encoder was built in `prepare`)
    reads_data: bool = True  # False: an `OnlineTask` and an encoder that fits nothing, so nothing is collected
    untrained: list[Encoder] = field(default_factory=list, compare=False, repr=False)  # handed to the first
    # `build_encoder`, so that the encoder (and its base's weights) is constructed once per run

    def without_encoder(self) -> PreparedRun:
        """The plan without the untrained encoder it holds (a sweep keeps many plans, not their weights)."""
        return replace(self, untrained=[])

    @property
    def dataset_key(self) -> str:
        """The identity of the task's dataset, collected or not (`data.dataset.dataset_id`)."""
        return dataset_id(self.task.dataset_config, self.task.collector)


def run_id_of(prepared: PreparedRun, dataset_fingerprint: str | None) -> str:
    """The id of `prepared` on the dataset with `dataset_fingerprint` (None: a run that reads no data)."""
    return identity.run_id(prepared.config, prepared.preset, prepared.request.seed, dataset_fingerprint,
                           prepared.code, prepared.placement.identity(), prepared.base)


def encoder_key_of(prepared: PreparedRun, dataset_fingerprint: str, placement: Placement | None = None) -> str:
    """The key of the trained encoder that `prepared` fits or reuses: on `placement`, where it trains (by
    default the run's; the CPU for an encoder that cannot move, see `place_encoder`)."""
    where = prepared.placement if placement is None else placement
    return identity.encoder_fit_key(prepared.config["encoder"], dataset_fingerprint, prepared.request.seed,
                                    prepared.code.encoder, prepared.base, where.identity())


def prepare(request: RunRequest) -> PreparedRun:
    """Resolve names, preset and overrides; build the task. Fails fast on bad input, before any work."""
    if request.seed < 0:
        raise BenchError(f"seed must be a non-negative integer, got {request.seed}")
    placement = resolve_device(request.device, request.deterministic)
    follow_device(placement.device)  # before anything renders
    encoder_entry = registry.get("encoders", request.encoder)
    task_entry = registry.get("tasks", request.task)
    preset, config = resolve_config(encoder_entry.spec, task_entry.spec, request.preset, request.overrides)
    spec = encoder_spec_from_config(encoder_entry.description, config["encoder"])  # validates overrides
    encoder_class = encoder_entry.load()  # a plugin that fails to import fails here, before any work
    task = task_entry.load()(config["task"], request.seed)
    if not isinstance(task, Task):
        raise BenchError(f"task {request.task!r} ({task_entry.entry_point.value}) does not implement the Task "
                         f"protocol (dataset_config, collector, evaluate, table)")
    if isinstance(task, DevicePlaced):
        task.to_device(placement.torch_device)
    dataset_config = task.dataset_config
    untrained = None
    if isinstance(dataset_config, Mapping):  # sizes that cannot work are refused before collecting anything
        check_dataset_config(dataset_config)
        untrained = _check_encoder(encoder_entry, config["encoder"], request.seed, dataset_config)
        length = dataset_config.get("episode_length")
        if isinstance(length, int) and spec.lookback > length:
            raise SpecError(f"encoder {spec.name!r} has a lookback of {spec.lookback} frames ({spec.frames} at "
                            f"stride {spec.stride}), longer than the task's {length}-frame episodes; use an "
                            f"encoder with lookback <= {length} or set task.dataset.episode_length >= "
                            f"{spec.lookback}")
    if untrained is not None and isinstance(task, ChecksEncoder):
        task.check_encoder(untrained)
    needs_fit = untrained is None or bool(untrained.needs_fit)
    if untrained is not None and untrained.needs_fit:
        fit_budget(spec.name, spec.train)  # a fit without a budget is refused before any work
    base = None if untrained is None else _base_identity(untrained)
    return PreparedRun(request, preset, config, encoder_entry, task, identity.run_code(encoder_class, task),
                       needs_fit, placement, base, reads_data=needs_fit or not isinstance(task, OnlineTask),
                       untrained=[] if untrained is None else [untrained])


def prepare_dataset(prepared: PreparedRun, home: BenchHome, show_progress: bool = True) -> MultiViewDataset | None:
    """The task's dataset, after whatever the task needs to collect it (an expert policy for demos); None,
    with nothing collected, for a run that reads no data (`PreparedRun.reads_data`)."""
    if not prepared.reads_data:
        return None
    if isinstance(prepared.task, NeedsArtifacts):
        prepared.task.prepare_artifacts(home, show_progress)
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
                    placement: Placement | None = None) -> Path:
    """The folder of the encoder this run fits or reuses (`encoder_key_of`; for a frozen base the key also
    holds the base's identity, its weights' checksum)."""
    key = encoder_key_of(prepared, dataset.fingerprint, placement)
    return home.encoders / f"{prepared.config['encoder']['name']}-{key}"


def frozen_base_of(encoder: Encoder) -> FrozenBase | None:
    """The encoder's frozen base when it declares one (the `FeatureCacheUser` capability)."""
    return encoder.frozen_base() if isinstance(encoder, FeatureCacheUser) else None


def _base_identity(encoder: Encoder) -> dict[str, Any] | None:
    base = frozen_base_of(encoder)
    return None if base is None else base.identity()


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


def construct_encoder(entry: registry.Entry, encoder_config: Mapping[str, Any], seed: int,
                      image_shape: tuple[int, int]) -> Encoder:
    """An encoder, constructed (untrained) for frames of `image_shape` (height, width)."""
    spec = encoder_spec_from_config(entry.description, encoder_config)
    encoder = entry.load()(spec, image_shape=image_shape, seed=seed)
    if not isinstance(encoder, Encoder):
        raise BenchError(f"encoder {spec.name!r} ({entry.entry_point.value}) does not "
                         f"implement the Encoder protocol (info, needs_fit, fit, embed, save, load)")
    return encoder


def _check_encoder(entry: registry.Entry, encoder_config: Mapping[str, Any], seed: int,
                   dataset_config: Mapping[str, Any]) -> Encoder | None:
    """Refuse, before any data is collected, an encoder that trains on more camera views than the task's
    dataset has (constructing it also refuses a model table it cannot build, or weights it cannot load);
    returns the untrained encoder (None: the dataset names no frame size to build it for)."""
    cameras = list(dataset_config.get("cameras", ()))
    shape = (dataset_config.get("height"), dataset_config.get("width"))
    if not all(isinstance(x, int) for x in shape):
        return None
    encoder = construct_encoder(entry, encoder_config, seed, shape)
    declared_inputs(encoder)  # an unknown declaration is refused here, before any data is collected
    if isinstance(encoder, MultiViewTrainer) and encoder.training_views > len(cameras):
        raise SpecError(f"encoder {entry.name!r} trains on {encoder.training_views} camera views of each "
                        f"moment; the task's dataset has {len(cameras)} ({', '.join(cameras) or 'none'}): give "
                        f"task.dataset.cameras at least {encoder.training_views} cameras")
    return encoder


def place_encoder(encoder: Encoder, placement: Placement) -> Placement:
    """Move the encoder to the run's device when it can (`DevicePlaced`); returns where it computes: an
    encoder without `to_device` stays on the CPU."""
    if isinstance(encoder, DevicePlaced):
        encoder.to_device(placement.torch_device)
        return placement
    return CPU


def build_encoder(prepared: PreparedRun, dataset: MultiViewDataset | None, home: BenchHome,
                  show_progress: bool = True, fit_dir: Path | None = None) -> tuple[Encoder, dict[str, Any]]:
    """The encoder for this run, placed on the run's device, fitted on `dataset` or loaded from the shared
    checkpoint (with no dataset, a run that reads no data: the encoder as constructed). With `fit_dir` (a
    folder of the caller's own, `--force`) the fit happens there and the shared checkpoint is left alone.
    The plan's untrained encoder is used by the first call; a later one constructs its own."""
    spec = encoder_spec_from_config(prepared.encoder_entry.description, prepared.config["encoder"])
    if prepared.untrained:
        encoder = prepared.untrained.pop()
    else:
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
    bar, report = _progress_bar(spec.name, show_progress)
    try:
        fit_stats = encoder.fit(dataset_for(encoder, dataset), budget, report, workdir)
    except BaseException:
        if not any(workdir.iterdir()):  # nothing to resume from: leave no empty folder behind
            workdir.rmdir()
        raise
    finally:
        bar.close()
    encoder.save(model_path)
    atomic_write_bytes(fit_file, json.dumps(fit_stats, indent=1).encode())
    (workdir / "train_checkpoint.pt").unlink(missing_ok=True)
    return {"fitted": True, "reused": False, "checkpoint": str(model_path), **fit_stats}


def fit_curve(fit: Mapping[str, Any]) -> dict[str, list[float]] | None:
    """The learning curve the fit behind `fit` (build_encoder's record of it) wrote, if any."""
    if "checkpoint" not in fit:
        return None
    path = Path(fit["checkpoint"]).parent / FIT_CURVE
    return json.loads(path.read_text()) if path.exists() else None


class RerunWarning(BenchWarning):
    """`--force` gave a result that differs from the stored run of the same id."""


def run(request: RunRequest, home: BenchHome, show_progress: bool = True) -> RunOutcome:
    """Run (or reuse) one (encoder, task, preset, seed) and return its stored record; with
    `request.deterministic`, torch's deterministic algorithms hold for the run only."""
    began = time.monotonic()
    prepared = prepare(request)
    with determinism(prepared.placement):
        return _run(prepared, home, show_progress, began)


def _run(prepared: PreparedRun, home: BenchHome, show_progress: bool, began: float) -> RunOutcome:
    store = ResultStore(home.database)
    store.check_writable()
    warn_if_dirty()
    dataset = prepare_dataset(prepared, home, show_progress)
    after_data = time.monotonic()
    run_id = run_id_of(prepared, None if dataset is None else dataset.fingerprint)
    # Two processes asked for one run share `runs/<id>`: the second waits here, then finds the result stored.
    with exclusive_lock(home.runs / f".{run_id}.lock"):
        return _run_once(prepared, home, show_progress, began, dataset, after_data, run_id, store)


def _run_once(prepared: PreparedRun, home: BenchHome, show_progress: bool, began: float,
              dataset: MultiViewDataset | None, after_data: float, run_id: str, store: ResultStore) -> RunOutcome:
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
                                     fit_dir=run_dir / "encoder" if request.force else None)
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
    curves = result.curves
    if (fitted := fit_curve(fit)) is not None:
        curves = {**curves, "fit": fitted}
    placement_notes = [] if fit["device"] == prepared.placement.device else [
        f"encoder {request.encoder!r} has no to_device: it ran on the CPU, the task on {prepared.placement.device}"]
    if "train" in result.curves:  # the learning curve beside the result (matplotlib only when needed)
        from mftcn_bench.results.figure import plot_run_curve

        plot_run_curve(result.curves["train"], run_dir / "curve.png", f"{request.encoder} on {request.task}")
    record_id = run_id
    if existing is not None:
        if canonical_json(existing.metrics) == canonical_json(result.metrics):
            shutil.rmtree(run_dir, ignore_errors=True)  # reproduced: the stored record and folder stay
            return RunOutcome(existing, False, prepared.task.table(existing.metrics),
                              [*result.notes, f"--force: computed again, the same metrics as stored run {run_id}"])
        record_id = content_hash({"rerun_of": run_id, "metrics": result.metrics})
        warnings.warn(f"--force: run {run_id} gave other metrics this time (not deterministic on this machine?); "
                      f"the stored result stays, the new one is run {record_id}", RerunWarning, stacklevel=2)
    final_dir = home.runs / record_id
    if "checkpoint" in fit and request.force:  # the forced fit moves with the run's folder
        fit = {**fit, "checkpoint": str(final_dir / "encoder" / Path(fit["checkpoint"]).name)}
    record = RunRecord(
        run_id=record_id, encoder=request.encoder, task=request.task, preset=prepared.preset,
        seed=request.seed, dataset_id=None if dataset is None else dataset.fingerprint,
        config={**prepared.config, "preset": prepared.preset, "seed": request.seed,
                "encoder_info": asdict(encoder.info), "privileged": list(declared_inputs(encoder)),
                "code": prepared.code.as_dict(), "fit": fit,
                "notes": [*result.notes, *placement_notes],
                "dataset_path": None if dataset is None else str(dataset.root),
                "device": prepared.placement.record(),
                **({"rerun_of": run_id} if record_id != run_id else {})},
        versions=versions(), metrics=result.metrics,
        timings={"dataset_s": after_data - began, "fit_s": after_fit - after_data,
                 "evaluate_s": done - after_fit, "total_s": done - began},
        artifacts=str(final_dir),
        created_at=datetime.now(UTC).isoformat(timespec="seconds"),
        curves=curves,
    )
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
    return RunOutcome(record, False, prepared.task.table(result.metrics), [*result.notes, *placement_notes])
