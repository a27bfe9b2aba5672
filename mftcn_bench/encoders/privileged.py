"""Privileged inputs: what an encoder may read besides pixels, declared, never leaked.

A benchmark of visual representations ranks encoders that see pixels only. The simulator's true state and
the recorded actions reach an encoder only when its class declares them (`ReadsPrivileged`); any other
encoder gets a `Withheld` marker in their place (in `ClipBatch.state`, in a stream's pushes, in the
episodes that `fit` reads), and its first use of that marker ends the run with one line saying what was read
and how to declare it. A record says what its encoder declared (`"privileged"`), and boards rank encoders that
read the true state apart from the pixel encoders, as references.

A marker rather than `None`: `None` would fail deep in a plugin as a `TypeError` on `NoneType`, a traceback
that does not say the harness withheld the input; the marker fails at the same place with the reason.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace
from typing import TYPE_CHECKING, Any, NoReturn, Protocol, runtime_checkable

from mftcn_bench.core.errors import BenchError
from mftcn_bench.data.dataset import Episode, MultiViewDataset

if TYPE_CHECKING:
    from mftcn_bench.encoders.base import Encoder

# What an encoder may declare: the simulator's true state (per frame) and the action taken after each frame.
INPUTS: tuple[str, ...] = ("state", "action")
# Declaring this makes an encoder a reference (an upper bound), ranked apart from the pixel encoders. Actions
# are what a robot itself sent, observable without a simulator: an encoder that reads them (PVE's
# controllability prior) stays among the pixel encoders, and its record and board entry say so.
REFERENCE_INPUTS: frozenset[str] = frozenset({"state"})


class PrivilegedInputError(BenchError):
    """An encoder read an input it did not declare."""


@runtime_checkable
class ReadsPrivileged(Protocol):
    """Optional declaration: `privileged_inputs = ("state",)` (or `("action",)`, or both) for an encoder that
    reads the true state or the recorded actions. Without it an encoder gets neither."""

    privileged_inputs: tuple[str, ...]


def declared_inputs(encoder: object) -> tuple[str, ...]:
    """The privileged inputs the encoder declares, in `INPUTS` order; an unknown name is a one-line error."""
    if not isinstance(encoder, ReadsPrivileged):
        return ()
    declared = tuple(encoder.privileged_inputs)
    unknown = sorted(set(declared) - set(INPUTS))
    if unknown:
        raise BenchError(f"encoder {type(encoder).__name__} declares privileged_inputs {unknown}; allowed: "
                         f"{list(INPUTS)}")
    return tuple(name for name in INPUTS if name in declared)


def is_reference(privileged: Iterable[str]) -> bool:
    """Whether an encoder that reads these inputs is ranked as a reference, apart from pixel encoders."""
    return bool(REFERENCE_INPUTS & set(privileged))


class Withheld:
    """Stands where the harness withholds an input: every use of it raises `PrivilegedInputError`."""

    __slots__ = ("_what", "_encoder")

    def __init__(self, what: str, encoder: str) -> None:
        self._what, self._encoder = what, encoder

    def _refuse(self, *_: Any, **__: Any) -> NoReturn:
        where = {"state": "the true state (ClipBatch.state, a stream's state, Episode.state)",
                 "action": "the recorded actions (Episode.action)"}[self._what]
        raise PrivilegedInputError(
            f"encoder {self._encoder!r} read {where} without declaring it: pixel encoders get pixels only; "
            f"declare privileged_inputs = (\"{self._what}\",) on its class to read it (an encoder reading the "
            f"true state is then ranked apart, as a reference)")

    def __getattr__(self, name: str) -> NoReturn:
        if name.startswith("__") and name.endswith("__"):
            # copy, pickle and numpy probe optional hooks by name; a missing hook is not a read of the input
            raise AttributeError(name)
        self._refuse()

    def __reduce__(self) -> tuple[type[Withheld], tuple[str, str]]:
        # the marker crosses process boundaries (sweep workers, data loaders) as a marker
        return Withheld, (self._what, self._encoder)

    __getitem__ = __array__ = __len__ = __iter__ = __bool__ = __float__ = __int__ = _refuse
    __add__ = __radd__ = __sub__ = __rsub__ = __mul__ = __rmul__ = __truediv__ = __matmul__ = _refuse
    __eq__ = __lt__ = __gt__ = __neg__ = __abs__ = _refuse
    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"Withheld({self._what!r})"


def visible(encoder: Encoder, name: str, value: Any) -> Any:
    """`value` of the privileged input `name` as the encoder may see it: itself when declared (or when there
    is none to withhold), else a `Withheld` marker."""
    if value is None or isinstance(value, Withheld) or name in declared_inputs(encoder):
        return value
    return Withheld(name, encoder.info.name)


class DatasetView(MultiViewDataset):
    """A dataset whose episodes carry only what an encoder declared: states and actions withheld otherwise
    (frames and labels pass). What `fit` receives."""

    def __init__(self, dataset: MultiViewDataset, encoder: Encoder) -> None:
        super().__init__(dataset.root)
        self._encoder = encoder

    def load(self, index: int) -> Episode:
        episode = super().load(index)
        return replace(episode, state=visible(self._encoder, "state", episode.state),
                       action=visible(self._encoder, "action", episode.action))


def dataset_for(encoder: Encoder, dataset: MultiViewDataset) -> MultiViewDataset:
    """The dataset itself for an encoder that declares both inputs, else a view without the undeclared ones."""
    if set(declared_inputs(encoder)) == set(INPUTS):
        return dataset
    return DatasetView(dataset, encoder)
