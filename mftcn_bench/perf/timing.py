"""How the benchmark measures and judges: targets, rows, the work sizes, alternating timed blocks, the table.

Absolute times drift on a shared machine, so every figure is measured beside its reference, in the same
process, alternating blocks of the two (the order reversed every other round) so that a change of load
hits both (`alternate`). Every figure runs with one torch thread (`one_thread`), so a ratio is not an
artefact of thread counts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Target:
    """What a figure must reach: `ratio` (or `value`) `>=` or `<=` `bound`; `report` has no bound."""

    op: str  # ">=", "<=" or "report"
    bound: float = 0.0
    on: str = "ratio"  # "ratio" or "value"
    unit: str = "x"

    def met(self, value: float | None, ratio: float | None) -> bool | None:
        measured = ratio if self.on == "ratio" else value
        if self.op == "report" or measured is None or not math.isfinite(measured):
            return None
        return measured >= self.bound if self.op == ">=" else measured <= self.bound

    def __str__(self) -> str:
        return "report" if self.op == "report" else f"{self.op} {self.bound:g}{self.unit}"


@dataclass(frozen=True)
class BenchRow:
    """One measured figure beside its reference."""

    figure: str
    value: float
    unit: str
    reference: str  # what it is compared with
    reference_value: float | None
    ratio: float | None
    target: Target
    note: str = ""

    @property
    def met(self) -> bool | None:
        return self.target.met(self.value, self.ratio)

    def cells(self) -> dict[str, str]:
        ref = self.reference if self.reference_value is None else \
            f"{self.reference}: {_num(self.reference_value)} {self.unit}"
        met = {True: "yes", False: "NO", None: "report"}[self.met]
        return {"figure": self.figure, "value": f"{_num(self.value)} {self.unit}", "reference": ref,
                "ratio": "-" if self.ratio is None else f"{self.ratio:.2f}x", "target": str(self.target),
                "met": met}


def _num(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:.3g}"


def format_table(rows: Sequence[BenchRow]) -> str:
    """A markdown (github) table: figure, value, reference, ratio, target, met."""
    from tabulate import tabulate

    cells = [row.cells() for row in rows]
    return tabulate([list(c.values()) for c in cells], headers=list(cells[0]) if cells else [],
                    tablefmt="github", disable_numparse=True)


@dataclass(frozen=True)
class Sizes:
    """How much work each figure measures: `QUICK` (CI, a minute or two) or `FULL` (docs/PERFORMANCE.md)."""

    name: str
    rounds: int  # alternations of subject and reference (after one untimed warm-up round)
    render_frames: int  # frames per block
    render_rounds: int
    stream_steps: int  # pushes per block (short blocks, many rounds: load on a shared machine changes fast)
    stream_rounds: int
    ppo_envs: int
    ppo_pixel_steps: int  # agent steps per collected batch (one episode, action repeat 8) from pixels
    ppo_state_steps: int  # the same on true state
    ppo_block_s: float  # each alternation block collects batches for at least this long
    ppo_update_minibatches: int  # minibatches of the pixel-trunk PPO update per timed block
    data_train: int  # rendered cartpole episodes (96x48, 2 views) for training and reading
    data_length: int
    train_steps: int  # training steps per block
    embed_frames: int  # frames of the episode embedded per block
    probe_length: int  # frames per synthetic probe episode (160x160)
    probe_train: tuple[int, ...]  # train-episode counts embedded (plus one test episode each)
    probe_fit_fraction: float  # of the paper's 160,000 + 20,000 frames for the MLP fit's measurement
    probe_fit_epochs: int | None  # cap on the MLP's epochs there (None: the paper preset's)


QUICK = Sizes("quick", rounds=2, render_frames=4, render_rounds=4, stream_steps=5, stream_rounds=6,
              ppo_envs=8, ppo_pixel_steps=4, ppo_state_steps=25, ppo_block_s=1.0, ppo_update_minibatches=1,
              data_train=3, data_length=100,
              train_steps=2, embed_frames=60, probe_length=100, probe_train=(1,), probe_fit_fraction=0.1,
              probe_fit_epochs=2)
FULL = Sizes("full", rounds=4, render_frames=10, render_rounds=20, stream_steps=10, stream_rounds=24,
             ppo_envs=8, ppo_pixel_steps=25, ppo_state_steps=125, ppo_block_s=5.0, ppo_update_minibatches=4,
             data_train=4, data_length=400,
             train_steps=6, embed_frames=400, probe_length=1000, probe_train=(1, 4), probe_fit_fraction=1.0,
             probe_fit_epochs=None)


Block = Callable[[], tuple[float, float]]  # runs once; returns (work done, seconds it took)


def timed(fn: Callable[[], Any], work: float) -> Block:
    """A block that times `fn()` and counts `work` units for it."""

    def block() -> tuple[float, float]:
        began = time.perf_counter()
        fn()
        return work, time.perf_counter() - began

    return block


def steps_block(train: Callable[[Any], None], steps: int, clips_per_step: int) -> Block:
    """Runs `train(progress)` for `steps` steps; times the steps after the first (from the trainer's own
    progress calls, so pool loading at its start is not counted); work = clips."""

    def block() -> tuple[float, float]:
        stamps: list[float] = []
        train(lambda done, total, stats: stamps.append(time.perf_counter()))
        return float(clips_per_step * (len(stamps) - 1)), stamps[-1] - stamps[0]

    return block


def alternate(blocks: Mapping[str, Block], rounds: int, warmup: bool = True) -> dict[str, float]:
    """Work per second of each block, run `rounds` times in alternation (order reversed every other
    round) after one untimed warm-up round."""
    names = list(blocks)
    if warmup:
        for name in names:
            blocks[name]()
    work, seconds = dict.fromkeys(names, 0.0), dict.fromkeys(names, 0.0)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            done, took = blocks[name]()
            work[name] += done
            seconds[name] += took
    return {name: work[name] / seconds[name] for name in names}


def one_thread() -> None:
    """One torch thread, so that subject and reference get the same and a ratio is not about threads."""
    import torch

    torch.set_num_threads(1)
