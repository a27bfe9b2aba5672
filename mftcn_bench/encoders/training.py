"""Training loop for multi-view time-contrastive encoders (mfTCN, TCN): sample, embed, n-pairs, Adam.

Batches come from a pool of train episodes that is refreshed one episode at a time: decoded frames, or,
for a head on a frozen base, the episodes' cached base features (memory-mapped), so the loader never
decompresses a chunk per step and a head never runs its base. Checkpoints (model, optimizer, step, random states) are
written atomically every `checkpoint_every` steps; `fit` resumes from the last one after a kill.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from mftcn_bench.core.device import cuda_rng_state, restore_cuda_rng_state
from mftcn_bench.core.errors import DataError, SpecError, TrainingError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.data.dataset import Episode, MultiViewDataset
from mftcn_bench.encoders.base import FIT_CURVE, FitBudget, ProgressFn
from mftcn_bench.encoders.common import load_failure, parse_table, save_payload
from mftcn_bench.encoders.feature_cache import FeatureCache
from mftcn_bench.encoders.losses import multiview_npairs_loss
from mftcn_bench.encoders.sampling import BatchPlan, plan_batch


@dataclass(frozen=True)
class ContrastiveTrainConfig:
    """The `[train]` table of a time-contrastive encoder spec."""

    steps: int
    batch_timesteps: int
    episodes_per_batch: int
    alpha: int
    lr: float
    weight_decay: float
    reg_lambda: float
    episode_pool: int
    pool_refresh_steps: int
    checkpoint_every: int
    max_seconds: float = 0.0  # 0: no wall-clock limit
    heldout_every: int = 0    # steps between held-out n-pairs losses on test episodes (0: none)
    heldout_batches: int = 0  # fixed batches of test episodes that loss averages over

    def __post_init__(self) -> None:
        check_optimizer(self)

    @classmethod
    def from_table(cls, name: str, table: dict) -> ContrastiveTrainConfig:
        return parse_table(cls, name, "train", table)


# What a pool holds per episode: the decoded episode, or its per-frame arrays [views, T, ...] (features).
PoolItem = Episode | np.ndarray
EpisodeLoader = Callable[[int], PoolItem]


def views_of(item: PoolItem) -> np.ndarray:
    """The per-view, per-frame array [views, T, ...] of a pool item: frames or base features."""
    return item.frames if isinstance(item, Episode) else item


class EpisodePool:
    """A few train episodes (decoded by `load`, by default `dataset.load`); every `refresh_steps` one of
    them is swapped for another."""

    def __init__(self, dataset: MultiViewDataset, size: int, refresh_steps: int, rng: np.random.Generator,
                 members: list[int] | None = None, load: EpisodeLoader | None = None):
        self.dataset, self.refresh_steps, self.rng = dataset, refresh_steps, rng
        self.load: EpisodeLoader = load or dataset.load
        self.train = dataset.episodes("train")
        self.size = min(size, len(self.train))
        picked = members if members is not None else rng.choice(self.train, size=self.size, replace=False)
        self.episodes: dict[int, Any] = {int(i): self.load(int(i)) for i in picked}

    def step(self, step: int) -> None:
        if self.refresh_steps <= 0 or step == 0 or step % self.refresh_steps or self.size == len(self.train):
            return
        outside = [i for i in self.train if i not in self.episodes]
        drop = int(self.rng.choice(sorted(self.episodes)))
        add = int(self.rng.choice(outside))
        del self.episodes[drop]
        self.episodes[add] = self.load(add)

    def length(self, episode: int) -> int:
        return int(views_of(self.episodes[episode]).shape[1])


def gather_clips(pool: EpisodePool, episodes: np.ndarray, times: np.ndarray, frames: int,
                 stride: int) -> np.ndarray:
    """[views, K, n, ...]: the clip of every view at each (episode, time): uint8 frames [H, W, 3] per
    clip frame, or base features [C, h, w] for a pool of cached features."""
    index = clip_indices(times, frames, stride)
    rows = [views_of(pool.episodes[int(e)])[:, idx] for e, idx in zip(episodes, index, strict=True)]
    return np.stack(rows, axis=1)


@dataclass
class LossCurve:
    """The fit's loss curve: at each evaluated step, the mean training loss since the previous point and the
    held-out loss (`Evaluation`) at that step."""

    step: list[float] = field(default_factory=list)
    train_loss: list[float] = field(default_factory=list)
    heldout_loss: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, list[float]]:
        return {"step": self.step, "train_loss": self.train_loss, "heldout_loss": self.heldout_loss}


@dataclass(frozen=True)
class Evaluation:
    """A held-out loss, computed every `every` steps with the network in eval mode and without gradients."""

    every: int
    loss: Callable[[], float]


def _save_checkpoint(path: Path, net: torch.nn.Module, opt: torch.optim.Optimizer, step: int,
                     rng: np.random.Generator, pool: EpisodePool, curve: LossCurve) -> None:
    save_payload(path, {"model": net.state_dict(), "optimizer": opt.state_dict(), "step": step,
                        "pool": sorted(pool.episodes), "curve": json.dumps(curve.as_dict()),
                        "numpy_rng": json.dumps(rng.bit_generator.state),
                        "torch_rng": torch.get_rng_state(), "cuda_rng": cuda_rng_state()})


def check_optimizer(config: LoopConfig) -> None:
    """Adam's settings, refused when the encoder is built (before its feature cache or any training)."""
    if not (np.isfinite(config.lr) and config.lr > 0) or not config.weight_decay >= 0:
        raise SpecError(f"encoder.train.lr must be a finite number > 0 and encoder.train.weight_decay >= 0, "
                        f"got {config.lr} and {config.weight_decay}")


class LoopConfig(Protocol):
    """The `[train]` keys every trainer built on `run_training` has."""

    lr: float
    weight_decay: float
    episode_pool: int
    pool_refresh_steps: int
    checkpoint_every: int


# batch_loss(pool, rng) -> (loss, extra statistics for the progress report)
BatchLoss = Callable[[EpisodePool, np.random.Generator], tuple[torch.Tensor, dict[str, float]]]


def run_training(net: torch.nn.Module, dataset: MultiViewDataset, config: LoopConfig, budget: FitBudget,
                 progress: ProgressFn, workdir: Path, *, seed: int, batch_loss: BatchLoss,
                 load: EpisodeLoader | None = None, device: torch.device | None = None,
                 evaluation: Evaluation | None = None) -> dict[str, float]:
    """Adam on `batch_loss` for `budget.steps` steps, drawing batches from a pool of train episodes; `net`
    and `batch_loss` compute on `device` (checkpoints load onto it).

    Checkpoints (model, optimizer, step, pool members, loss curve, random states) go to
    `workdir/train_checkpoint.pt` every `checkpoint_every` steps and training resumes from there bit for bit.
    A non-finite loss stops training with the step. Returns {'final_loss', 'steps', 'seconds',
    'resumed_from_step'} (0 unless a checkpoint was found); with an `evaluation`, also 'heldout_loss' (at the
    last step), and the `LossCurve` goes to `workdir / FIT_CURVE`. The evaluation draws no random numbers and
    changes no weights or statistics, so the fitted network is the same with or without it."""
    check_optimizer(config)
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    trainable = [p for p in net.parameters() if p.requires_grad]  # a frozen base has none
    opt = torch.optim.Adam(trainable, lr=config.lr, weight_decay=config.weight_decay)
    workdir.mkdir(parents=True, exist_ok=True)
    checkpoint = workdir / "train_checkpoint.pt"
    start, members, curve = 0, None, LossCurve()
    if checkpoint.exists():
        try:
            state = torch.load(checkpoint, weights_only=True, map_location=device or "cpu")
            net.load_state_dict(state["model"])
            opt.load_state_dict(state["optimizer"])
        except Exception as exc:  # noqa: BLE001 - a truncated or foreign file
            raise TrainingError(f"training checkpoint {checkpoint} cannot be loaded ({load_failure(exc)}); "
                                f"rerun with --force (or delete it) to train from the start") from None
        start, members = int(state["step"]), [int(i) for i in state["pool"]]
        if "curve" in state:  # absent in checkpoints written before the held-out loss
            curve = LossCurve(**json.loads(state["curve"]))
        torch.set_rng_state(state["torch_rng"].cpu())
        restore_cuda_rng_state(state.get("cuda_rng"))
        rng.bit_generator.state = json.loads(state["numpy_rng"])
    pool = EpisodePool(dataset, config.episode_pool, config.pool_refresh_steps, rng, members, load)
    net.train()
    began, loss_value, done = time.monotonic(), float("nan"), start
    since_point: list[float] = []

    def evaluate(at: int) -> None:
        assert evaluation is not None
        net.eval()
        with torch.no_grad():
            heldout = evaluation.loss()
        net.train()
        curve.step.append(float(at))
        curve.train_loss.append(float(np.mean(since_point)) if since_point else float("nan"))
        curve.heldout_loss.append(heldout)
        since_point.clear()

    for step in range(start, budget.steps):
        pool.step(step)
        loss, stats = batch_loss(pool, rng)
        loss_value = float(loss.detach())
        if not np.isfinite(loss_value):
            raise TrainingError(f"training loss became {loss_value} at step {step}; no result was written "
                                f"(try a lower encoder.train.lr than {config.lr:g})")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        done = step + 1
        since_point.append(loss_value)
        if evaluation is not None and evaluation.every and done % evaluation.every == 0:
            evaluate(done)
        progress(done, budget.steps, {"loss": loss_value, **stats})
        if config.checkpoint_every and done % config.checkpoint_every == 0 and done < budget.steps:
            _save_checkpoint(checkpoint, net, opt, done, rng, pool, curve)
        if budget.max_seconds and time.monotonic() - began > budget.max_seconds:
            break
    if evaluation is not None and evaluation.every and (not curve.step or curve.step[-1] != done):
        evaluate(done)  # the fitted network's held-out loss, wherever the budget ended
    net.eval()
    result = {"final_loss": loss_value, "steps": float(done), "seconds": time.monotonic() - began,
              "resumed_from_step": float(start)}
    if evaluation is not None and evaluation.every:
        result["heldout_loss"] = curve.heldout_loss[-1]
        atomic_write_bytes(workdir / FIT_CURVE, json.dumps(curve.as_dict()).encode())
    return result


@runtime_checkable
class BaseFeatureHead(Protocol):
    """A clip network that can embed clips of cached base features [B, n, C, h, w]."""

    def head_on_base(self, features: torch.Tensor) -> torch.Tensor: ...


def train_multiview(net: torch.nn.Module, dataset: MultiViewDataset, config: ContrastiveTrainConfig,
                    budget: FitBudget, progress: ProgressFn, workdir: Path, *, frames: int, stride: int,
                    seed: int, features: FeatureCache | None = None,
                    device: torch.device | None = None) -> dict[str, float]:
    """Train `net` (uint8 clips [B, n, 3, H, W] -> [B, D]) with multi-view n-pairs; with `features`, on clips
    of cached base features through `net.head_on_base` (a `BaseFeatureHead`) instead of frames. Batches go
    to `device` (where `net` is) once a step.

    With `heldout_every` and `heldout_batches` set and test episodes in the dataset, the n-pairs loss of
    `heldout_batches` batches of test episodes, planned once from the seed as training plans its batches,
    is recorded every `heldout_every` steps and at the end (`run_training`'s 'heldout_loss' and curve); with
    too few test frames for a batch of the training's size (toy data) there is none."""
    target = device or torch.device("cpu")
    if len(dataset.cameras) < 2:
        raise SpecError("time-contrastive training needs a dataset with at least two camera views")
    lookback = (frames - 1) * stride + 1
    shortest = min(dataset.episode_length(i) for i in dataset.episodes("train"))
    if lookback > shortest:
        raise SpecError(f"lookback of {lookback} frames is longer than the shortest train episode "
                        f"({shortest} frames); use a smaller frames/stride or longer episodes")
    min_gap = max(config.alpha, lookback)
    load: EpisodeLoader | None = None
    if features is None:
        def embed(batch: np.ndarray) -> torch.Tensor:
            return net(torch.from_numpy(batch).to(target).permute(0, 1, 4, 2, 3))
    else:
        if not isinstance(net, BaseFeatureHead):
            raise TypeError(f"{type(net).__name__} cannot train on cached features: it has no head_on_base")
        head, load = net, features.load

        def embed(batch: np.ndarray) -> torch.Tensor:
            return head.head_on_base(torch.from_numpy(batch).to(target))

    def plan_loss(pool: EpisodePool, plan: BatchPlan) -> torch.Tensor:
        clips = gather_clips(pool, plan.episodes, plan.times, frames, stride)
        views, count = clips.shape[:2]
        embeddings = embed(clips.reshape(views * count, *clips.shape[2:])).reshape(views, count, -1)
        return multiview_npairs_loss(embeddings, config.reg_lambda)

    def batch_loss(pool: EpisodePool, rng: np.random.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        lengths = {i: pool.length(i) for i in pool.episodes}
        plan = plan_batch(rng, sorted(pool.episodes), lengths, config.batch_timesteps,
                          config.episodes_per_batch, min_gap)
        return plan_loss(pool, plan), {}

    evaluation = None
    test = dataset.episodes("test")
    plans: list[BatchPlan] = []
    if config.heldout_every and config.heldout_batches and test:
        # Its own generator: the training batches are those of a fit without the held-out loss.
        heldout_rng = np.random.default_rng([seed, 1])
        lengths = {i: dataset.episode_length(i) for i in test}
        try:
            plans = [plan_batch(heldout_rng, sorted(test), lengths, config.batch_timesteps,
                                config.episodes_per_batch, min_gap) for _ in range(config.heldout_batches)]
        except DataError:  # too few test frames for a batch of the training's size (toy data)
            plans = []
    if plans:
        used = sorted({int(e) for plan in plans for e in plan.episodes})  # loaded once, kept for the fit
        heldout = EpisodePool(dataset, len(used), 0, heldout_rng, members=used, load=load)
        evaluation = Evaluation(config.heldout_every,
                                lambda: float(np.mean([float(plan_loss(heldout, plan)) for plan in plans])))

    return run_training(net, dataset, config, budget, progress, workdir, seed=seed, batch_loss=batch_loss,
                        load=load, device=device, evaluation=evaluation)
