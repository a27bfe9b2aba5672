"""Multi-view batch sampling for time-contrastive training.

A batch is K time steps, drawn from a few episodes; for each time step, one clip per view. Within an
episode the sampled time steps are at least `min_gap = max(alpha, lookback)` frames apart, so clips of
different time steps never share a frame and are at least alpha apart in time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mftcn_bench.core.errors import DataError


def sample_timesteps(rng: np.random.Generator, length: int, count: int, min_gap: int) -> np.ndarray:
    """`count` sorted time steps in [0, length) with consecutive gaps >= min_gap, uniformly among all
    such sets (choose distinct points in a shrunk range, then spread them back out)."""
    slack = length - (count - 1) * (min_gap - 1)
    if count < 1 or slack < count:
        raise DataError(f"cannot sample {count} time steps at least {min_gap} frames apart from an episode "
                        f"of {length} frames; use longer episodes, fewer time steps or a smaller window")
    chosen = np.sort(rng.choice(slack, size=count, replace=False))
    return chosen + np.arange(count) * (min_gap - 1)


@dataclass(frozen=True)
class BatchPlan:
    """Which (episode, time step) pairs make up one batch; row k is time step k of every view."""

    episodes: np.ndarray  # [K] episode index of each time step
    times: np.ndarray  # [K] time step within its episode


def plan_batch(rng: np.random.Generator, episodes: list[int], lengths: dict[int, int], timesteps: int,
               episodes_per_batch: int, min_gap: int) -> BatchPlan:
    """K = `timesteps` time steps split as evenly as possible over `episodes_per_batch` distinct
    episodes drawn from `episodes`."""
    per_batch = min(episodes_per_batch, len(episodes), timesteps)
    picked = rng.choice(episodes, size=per_batch, replace=False)
    counts = np.full(per_batch, timesteps // per_batch)
    counts[: timesteps % per_batch] += 1
    eps, times = [], []
    for episode, count in zip(picked, counts, strict=True):
        eps.append(np.full(count, episode))
        times.append(sample_timesteps(rng, lengths[int(episode)], int(count), min_gap))
    return BatchPlan(np.concatenate(eps), np.concatenate(times))
