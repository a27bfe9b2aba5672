"""Streaming inference for clip encoders with a per-frame base and a temporal head (mfTCN, TCN).

A rollout sees one new frame per environment per step. Re-embedding the whole clip each step runs the
base CNN on all n frames of it; `StreamingEmbedder` keeps a ring buffer of per-frame base features per
environment covering the lookback window ((n - 1) * s + 1 frames), so each step costs one base-CNN
forward for the new frames plus the temporal head, whatever the lookback.

At an episode start the environment's whole buffer is filled with the first frame's features: the clip
rule of `mftcn_bench.data.clips` (indices before the first frame clamp to it), so the outputs equal the
encoder's batch embeddings of the same episode.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch

from mftcn_bench.data.clips import clip_offsets


class FrameHeadNet(Protocol):
    """A network split into a per-frame base and a head over a clip's stacked per-frame features."""

    def frame_features(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 [N, 3, H, W] -> features [N, C, h, w]."""
        ...

    def head(self, features: torch.Tensor) -> torch.Tensor:
        """[B, n, C, h, w] -> embeddings [B, D]."""
        ...


class StreamingEmbedder:
    """Embeds the clip ending at each new frame of `num_envs` environments stepped together."""

    def __init__(self, net: FrameHeadNet, frames: int, stride: int, num_envs: int) -> None:
        if frames < 1 or stride < 1 or num_envs < 1:
            raise ValueError(f"frames, stride and num_envs must be >= 1, got {frames}, {stride}, {num_envs}")
        self.net, self.frames, self.stride, self.num_envs = net, frames, stride, num_envs
        self.lookback = (frames - 1) * stride + 1
        self._offsets = torch.from_numpy(clip_offsets(frames, stride))
        self._buffer: torch.Tensor | None = None  # [E, lookback, C, h, w], allocated at the first push
        self._slot = -1  # ring position of the newest frame
        self._started = np.zeros(num_envs, dtype=bool)

    def reset(self) -> None:
        """Forget every environment's history (the next push must start an episode in all of them)."""
        self._buffer, self._slot = None, -1
        self._started[:] = False

    @torch.no_grad()
    def observe(self, frames: np.ndarray, episode_start: np.ndarray, state: np.ndarray | None = None) -> None:
        """Take new frames uint8 [E, H, W, 3] (and which environments start an episode with them, bool [E])
        into the history without embedding: for frames whose embedding nobody reads (the inner steps of an
        action repeat). `state` is not used."""
        frames = np.asarray(frames)
        start = np.asarray(episode_start, dtype=bool).reshape(-1)
        if frames.ndim != 4 or frames.shape[0] != self.num_envs or frames.shape[-1] != 3:
            raise ValueError(f"frames must be [{self.num_envs}, H, W, 3], got {frames.shape}")
        if start.shape != (self.num_envs,):
            raise ValueError(f"episode_start must have {self.num_envs} entries, got {start.shape}")
        started = self._started | start
        if not started.all():
            raise ValueError(f"environments {np.flatnonzero(~started).tolist()} have not started an episode")
        self._started = started
        images = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2)
        features = self.net.frame_features(images)  # [E, C, h, w]
        if self._buffer is None or self._buffer.shape[2:] != features.shape[1:]:
            self._buffer = features.new_zeros((self.num_envs, self.lookback, *features.shape[1:]))
        self._slot = (self._slot + 1) % self.lookback
        self._buffer[:, self._slot] = features
        restart = torch.from_numpy(np.flatnonzero(start))
        if len(restart):
            self._buffer[restart] = features[restart].unsqueeze(1)

    @torch.no_grad()
    def push(self, frames: np.ndarray, episode_start: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """New frames uint8 [E, H, W, 3] and which environments start an episode with them (bool [E])
        -> float32 [E, D], the embedding of the clip ending at each new frame. `state` is not used."""
        self.observe(frames, episode_start, state)
        index = (self._slot + self._offsets) % self.lookback  # ring slots of frames t-(n-1)s, ..., t
        return self.net.head(self._buffer[:, index]).numpy().astype(np.float32, copy=False)
