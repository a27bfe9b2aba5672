"""Clip indexing shared by training, batch embedding and streaming rollouts.

The clip at time t of one view is frames t-(n-1)s, ..., t-s, t (oldest first). Near an episode's start,
indices before the first frame are clamped to it: the first frames of an episode repeat the first frame.
The same rule is used when training, when embedding a dataset, and in streaming rollouts.
"""

from __future__ import annotations

import numpy as np


def clip_offsets(frames: int, stride: int) -> np.ndarray:
    """Offsets from t of a clip's frames, oldest first: [-(n-1)s, ..., -s, 0]."""
    return (np.arange(frames) - (frames - 1)) * stride


def clip_indices(times: np.ndarray, frames: int, stride: int) -> np.ndarray:
    """[len(times), frames] frame indices of the clips ending at `times`, clamped at the episode start."""
    times = np.asarray(times, dtype=np.int64)
    return np.maximum(times[:, None] + clip_offsets(frames, stride)[None, :], 0)


class ClipRing:
    """The last `lookback` per-frame items (frames, states or base features; numpy arrays or torch tensors)
    of `num_envs` environments stepped together, and the clip ending at the newest one.

    An environment that starts an episode has its whole history set to its first item: the clamping rule
    above, so a rollout's clips equal the clips `clip_indices` builds from the recorded episode."""

    def __init__(self, frames: int, stride: int, num_envs: int) -> None:
        if frames < 1 or stride < 1 or num_envs < 1:
            raise ValueError(f"frames, stride and num_envs must be >= 1, got {frames}, {stride}, {num_envs}")
        self.num_envs, self.lookback = num_envs, (frames - 1) * stride + 1
        self._offsets = clip_offsets(frames, stride)
        self._buffer = None  # [E, lookback, ...], allocated from the first push
        self._slot = -1      # ring position of the newest item
        self._started = np.zeros(num_envs, dtype=bool)

    def push(self, items, episode_start: np.ndarray) -> None:
        """Take each environment's newest item [E, ...]; `episode_start` (bool [E]) marks a first item."""
        start = np.asarray(episode_start, dtype=bool).reshape(-1)
        if start.shape != (self.num_envs,) or len(items) != self.num_envs:
            raise ValueError(f"expected {self.num_envs} items and episode_start flags, got {len(items)} and "
                             f"{start.shape}")
        started = self._started | start
        if not started.all():
            raise ValueError(f"environments {np.flatnonzero(~started).tolist()} have not started an episode")
        self._started = started
        if self._buffer is None or tuple(self._buffer.shape[2:]) != tuple(items.shape[1:]):
            self._buffer = _tile(items, self.lookback)
        self._slot = (self._slot + 1) % self.lookback
        self._buffer[:, self._slot] = items
        restart = np.flatnonzero(start)
        if len(restart):
            self._buffer[restart] = _tile(items[restart], self.lookback)

    def clip(self):
        """[E, n, ...]: each environment's clip ending at its newest item, oldest first (a copy)."""
        index = (self._slot + self._offsets) % self.lookback
        return self._buffer[:, index]

    def reset(self) -> None:
        """Forget every environment's history (the next push must start an episode in all of them)."""
        self._buffer, self._slot = None, -1
        self._started[:] = False


def _tile(items, lookback: int):
    """[E, ...] -> [E, lookback, ...], each item repeated (numpy or torch, whichever `items` is)."""
    if isinstance(items, np.ndarray):
        return np.repeat(items[:, None], lookback, axis=1)
    return items.unsqueeze(1).repeat(1, lookback, *([1] * (items.dim() - 1)))
