"""What a task asks of its encoder beyond the encoder contract, checked before any work.

Kept out of `tasks.base` on purpose: the runner imports that module, and a run's identity holds the code of
the runner's imports, so a new capability there would re-key every stored result. The command line and
the sweep planner, which are not part of a run's identity, call `check_task_accepts` on each planned run
before anything is trained or collected.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from mftcn_bench.encoders.base import Encoder


@runtime_checkable
class EncoderRequirements(Protocol):
    """A task that serves only some encoders (imitation refuses one trained with a policy)."""

    def check_encoder(self, encoder: Encoder) -> None:
        """Raise a one-line `SpecError` naming what is allowed when the task cannot serve `encoder`."""
        ...


def check_task_accepts(task: object, encoders: list[Encoder]) -> None:
    """`task.check_encoder` on each untrained encoder of a planned run, when the task has requirements."""
    if isinstance(task, EncoderRequirements):
        for encoder in encoders:
            task.check_encoder(encoder)
