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
