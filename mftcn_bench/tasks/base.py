"""The task contract: a task names the dataset it needs and turns a frozen encoder into metrics."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from mftcn_bench.data.dataset import Collector, MultiViewDataset
from mftcn_bench.encoders.base import Encoder

if TYPE_CHECKING:
    from mftcn_bench.core.home import BenchHome
    from mftcn_bench.rl.expert import ExpertSetup

# Learning curves: name -> columns of equal length, e.g.
# {"train": {"frames": [...], "wall_s": [...], "return": [...]}}.
Curves = dict[str, dict[str, list[float]]]


@dataclass(frozen=True)
class TaskResult:
    """Metrics of one run (floats, or None for "not applicable"), notes shown with the table, and the
    learning curves of tasks that train something (stored with the result)."""

    metrics: dict[str, float | None]
    notes: list[str] = field(default_factory=list)
    curves: Curves = field(default_factory=dict)


@runtime_checkable
class Task(Protocol):
    """Constructed as `cls(config, seed)` from the resolved `task` table. Optional capabilities:
    `OnlineTask`, `ChecksEncoder`, `NeedsArtifacts`, `ShowsProgress`, `LabelledTask`."""

    @property
    def dataset_config(self) -> Mapping[str, Any]: ...

    @property
    def collector(self) -> Collector: ...

    def evaluate(self, encoder: Encoder, dataset: MultiViewDataset, workdir: Path) -> TaskResult:
        """Metrics of the frozen encoder. `workdir` is the run's own folder (the same on a rerun of the same
        run): checkpoints of long evaluations go there, so a killed run resumes; plots too."""
        ...

    def table(self, metrics: Mapping[str, Any]) -> list[dict[str, Any]]:
        """Rows of the printed result table."""
        ...


@runtime_checkable
class OnlineTask(Protocol):
    """A task that measures the encoder in the simulator (PPO) and reads its dataset only to fit the
    encoder: with an encoder that fits nothing (true state, random state, a frozen base alone, pixels-cnn)
    the runner collects no data and calls `evaluate_online`."""

    def evaluate_online(self, encoder: Encoder, workdir: Path) -> TaskResult: ...


@runtime_checkable
class ChecksEncoder(Protocol):
    """A task that serves only some encoders (imitation refuses one trained with a policy): the runner asks
    it about the untrained encoder while planning, before any work."""

    def check_encoder(self, encoder: Encoder) -> None:
        """Raise a one-line `SpecError` naming what is allowed when the task cannot serve `encoder`."""
        ...


@runtime_checkable
class NeedsArtifacts(Protocol):
    """A task that needs something built before its data can be collected (the cheetah task's expert
    policy); the runner calls `prepare_artifacts` first."""

    def prepare_artifacts(self, home: BenchHome, show_progress: bool = True) -> None: ...


@runtime_checkable
class RecordsExpert(Protocol):
    """A task whose data are a true-state expert's demonstrations: what trains that expert (its environment
    as the state sees it, its PPO settings, its seed), for `mftcn-bench expert train`, and the data set its
    demonstrations are recorded as, for `mftcn-bench expert demos`."""

    expert: ExpertSetup

    @property
    def demos_config(self) -> Mapping[str, Any]: ...


@runtime_checkable
class ShowsProgress(Protocol):
    """A task with progress bars of its own (PPO's); the runner passes `--no-progress` on before evaluating."""

    def show_progress(self, enabled: bool) -> None: ...


@runtime_checkable
class LabelledTask(Protocol):
    """A task whose episodes carry per-frame labels (pouring): `mftcn-bench data show` captions them."""

    label_names: Sequence[str]
    label_formats: Mapping[str, Sequence[str]] | None
