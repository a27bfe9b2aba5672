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

from mftcn_bench.data.clips import ClipRing


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

    def __init__(self, net: FrameHeadNet, frames: int, stride: int, num_envs: int,
                 device: torch.device | None = None) -> None:
        self.net, self.frames, self.stride, self.num_envs = net, frames, stride, num_envs
        self.device = device or torch.device("cpu")  # where `net` is: frames go there once, embeddings come back
        self._ring = ClipRing(frames, stride, num_envs)  # per-frame base features [E, lookback, C, h, w]
        self.lookback = self._ring.lookback

    def reset(self) -> None:
        """Forget every environment's history (the next push must start an episode in all of them)."""
        self._ring.reset()

    @torch.no_grad()
    def observe(self, frames: np.ndarray, episode_start: np.ndarray, state: np.ndarray | None = None) -> None:
        """Take new frames uint8 [E, H, W, 3] (and which environments start an episode with them, bool [E])
        into the history without embedding: for frames whose embedding nobody reads (the inner steps of an
        action repeat). `state` is not used."""
        frames = np.asarray(frames)
        if frames.ndim != 4 or frames.shape[0] != self.num_envs or frames.shape[-1] != 3:
            raise ValueError(f"frames must be [{self.num_envs}, H, W, 3], got {frames.shape}")
        images = torch.from_numpy(np.ascontiguousarray(frames)).to(self.device).permute(0, 3, 1, 2)
        self._ring.push(self.net.frame_features(images), episode_start)  # one base pass per new frame

    @torch.no_grad()
    def push(self, frames: np.ndarray, episode_start: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """New frames uint8 [E, H, W, 3] and which environments start an episode with them (bool [E])
        -> float32 [E, D], the embedding of the clip ending at each new frame. `state` is not used."""
        self.observe(frames, episode_start, state)
        return self.net.head(self._ring.clip()).cpu().numpy().astype(np.float32, copy=False)
