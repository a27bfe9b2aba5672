"""The plan of one run: a request (`RunRequest`) resolved against the registry and the specs into what the run
will do and need (`PreparedRun`), and the identities it is keyed by (`run_id_of`, `encoder_key_of`).

Planning refuses bad input before any work: unknown names, impossible sizes, a lookback longer than the
episodes, an encoder that trains on more camera views than the data set has or that has no fit budget. To
learn whether the run reads data, fits, and which frozen base it keys, the plan constructs the untrained
encoder once; `prepare_with_encoder` hands it back beside the plan, so that the run's build
(`run.artifacts.build_encoder`) uses it instead of constructing it again, while the plan itself holds no
encoder (a sweep keeps many plans, not their weights).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from mftcn_bench.core import identity, registry
from mftcn_bench.core.device import CPU, DevicePlaced, Placement, resolve_device
from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.specs import encoder_spec_from_config, resolve_config
from mftcn_bench.data.dataset import check_dataset_config, dataset_id
from mftcn_bench.encoders.base import Encoder, MultiViewTrainer, fit_budget
from mftcn_bench.encoders.privileged import declared_inputs
from mftcn_bench.run.construct import construct_encoder, frozen_base_of
from mftcn_bench.sim.rendering import follow_device
from mftcn_bench.tasks.base import ChecksEncoder, OnlineTask, Task


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
class PreparedRun:
    """The plan of one run: the request resolved against the registry and specs, its task built, and what
    the run will need (a dataset or none, a fit or none), learnt from the untrained encoder built once in
    `prepare_with_encoder`. `run` and the sweep's phases (`orchestration.sweep`) both work from it."""

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
    default the run's; the CPU for an encoder that cannot move, see `run.artifacts.place_encoder`)."""
    where = prepared.placement if placement is None else placement
    return identity.encoder_fit_key(prepared.config["encoder"], dataset_fingerprint, prepared.request.seed,
                                    prepared.code.encoder, prepared.base, where.identity())


def prepare(request: RunRequest) -> PreparedRun:
    """Resolve names, preset and overrides; build the task. Fails fast on bad input, before any work. The
    encoder constructed to plan the run is dropped (`prepare_with_encoder` keeps it)."""
    prepared, _ = prepare_with_encoder(request)
    return prepared


def prepare_with_encoder(request: RunRequest) -> tuple[PreparedRun, Encoder | None]:
    """`prepare`, and the untrained encoder it constructed for the plan (None: the task's dataset names no
    frame size to construct it for). Hand that encoder to one `build_encoder` of this plan, which then
    need not construct it (and load its base's weights) again."""
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
    prepared = PreparedRun(request, preset, config, encoder_entry, task, identity.run_code(encoder_class, task),
                           needs_fit, placement, base, reads_data=needs_fit or not isinstance(task, OnlineTask))
    return prepared, untrained


def _base_identity(encoder: Encoder) -> dict[str, Any] | None:
    base = frozen_base_of(encoder)
    return None if base is None else base.identity()


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
