"""Pieces shared by the single-frame encoders (pixels-cnn, PVE, Shuffle and Learn).

- `FrameNet`: the mfTCN base CNN (`BaseCNN`, with its optional coordinate channels), a spatial average
  and a linear layer: one uint8 frame -> a vector.
- `parse_table`: a spec's `[model]` or `[train]` table -> a frozen dataclass; an unknown or missing key is
  a one-line `SpecError`.
- `train_single_view`: Adam on a loss computed from a pool of decoded train episodes (the mfTCN trainer's
  `EpisodePool`), with the same atomic checkpoints and bitwise resume as `training.train_multiview`, and
  a NaN loss stopping with the step.
- `save_network` / `load_network`: atomic checkpoint of a module's weights plus the image shape.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
from torch import nn

from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import FitBudget, ProgressFn
from mftcn_bench.encoders.mftcn import BaseCNN, MfTCNModelConfig
from mftcn_bench.encoders.training import BatchLoss, run_training
from mftcn_bench.errors import BenchError, SpecError

T = TypeVar("T")


def parse_table(cls: type[T], encoder: str, section: str, table: Mapping[str, Any]) -> T:
    """A frozen dataclass from a spec table; unknown or missing keys are a one-line SpecError."""
    known = [f.name for f in fields(cls)]  # type: ignore[arg-type] - cls is a dataclass
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise SpecError(f"encoder {encoder!r}: unknown key(s) {unknown} in [{section}]; allowed: {sorted(known)}")
    try:
        return cls(**dict(table))
    except TypeError as exc:
        raise SpecError(f"encoder {encoder!r}: bad [{section}] table ({exc})") from None


@dataclass(frozen=True, kw_only=True)
class CNNConfig:
    """The convolution part of a `[model]` table: the mfTCN base CNN's layers."""

    channels: list[int]
    kernels: list[int]
    strides: list[int]
    coords: bool = True

    def __post_init__(self) -> None:
        if not (len(self.channels) == len(self.kernels) == len(self.strides) >= 1):
            raise SpecError("[model]: channels, kernels and strides must be lists of one length")

    def base_config(self) -> MfTCNModelConfig:
        """The mfTCN model config that `BaseCNN` reads (it uses only the convolution fields)."""
        return MfTCNModelConfig(list(self.channels), list(self.kernels), list(self.strides),
                                temporal_channels=0, coords=self.coords)


class FrameNet(nn.Module):
    """uint8 frames [N, 3, H, W] -> [N, out_dim]: BaseCNN, spatial average, linear layer."""

    def __init__(self, config: CNNConfig, out_dim: int) -> None:
        super().__init__()
        self.base = BaseCNN(config.base_config())
        self.fc = nn.Linear(self.base.out_channels, out_dim)

    def pooled(self, images: torch.Tensor) -> torch.Tensor:
        """Spatially averaged base-CNN features [N, C]."""
        return self.base(images).mean(dim=(2, 3))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.fc(self.pooled(images))


def to_images(frames: np.ndarray) -> torch.Tensor:
    """uint8 numpy frames [..., H, W, 3] -> uint8 tensor [..., 3, H, W]."""
    tensor = torch.from_numpy(np.ascontiguousarray(frames))
    return tensor.movedim(-1, -3)


def check_image_shape(expected: tuple[int, int], dataset: MultiViewDataset) -> None:
    if dataset.image_shape != expected:
        raise SpecError(f"encoder built for {expected} images cannot train on {dataset.image_shape} frames")


def save_network(path: Path, net: nn.Module, image_shape: tuple[int, int]) -> None:
    """Weights and image shape, written to a temporary file and renamed."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save({"model": net.state_dict(), "image_shape": list(image_shape)}, tmp)
    os.replace(tmp, path)


def load_network(path: Path, net: nn.Module, image_shape: tuple[int, int]) -> None:
    """Inverse of `save_network`; a bad file or another image shape is a one-line error."""
    try:
        state = torch.load(path, weights_only=True)
        net.load_state_dict(state["model"])
    except Exception as exc:  # noqa: BLE001 - truncated, foreign or mismatched file
        raise BenchError(f"encoder checkpoint {path} cannot be loaded ({type(exc).__name__}); "
                         f"delete it to train again") from None
    if tuple(state["image_shape"]) != tuple(image_shape):
        raise SpecError(f"encoder checkpoint {path} was trained on {tuple(state['image_shape'])} images, "
                        f"not {tuple(image_shape)}")
    net.eval()


@dataclass(frozen=True, kw_only=True)
class SingleViewTrainConfig:
    """`[train]` keys common to the single-view trainers."""

    steps: int
    batch_size: int
    lr: float
    weight_decay: float
    episode_pool: int
    pool_refresh_steps: int
    checkpoint_every: int
    camera_index: int = 0
    max_seconds: float = 0.0  # 0: no wall-clock limit

    def __post_init__(self) -> None:
        for key in ("steps", "episode_pool", "pool_refresh_steps", "checkpoint_every", "camera_index"):
            if getattr(self, key) < 0:
                raise SpecError(f"[train]: {key} must be >= 0, got {getattr(self, key)}")
        if self.batch_size < 1 or self.episode_pool < 1:
            raise SpecError(f"[train]: batch_size and episode_pool must be >= 1, got {self.batch_size} "
                            f"and {self.episode_pool}")
        if not self.lr > 0:
            raise SpecError(f"[train]: lr must be > 0, got {self.lr}")


def train_single_view(net: nn.Module, dataset: MultiViewDataset, config: SingleViewTrainConfig,
                      budget: FitBudget, progress: ProgressFn, workdir: Path, *, seed: int, min_length: int,
                      batch_loss: BatchLoss) -> dict[str, float]:
    """Adam on `batch_loss` for `budget.steps` steps; returns {'final_loss', 'steps', 'seconds'}.

    Checkpoints (model, optimizer, step, pool members, random states) go to
    `workdir/train_checkpoint.pt` every `checkpoint_every` steps, and training resumes from there.
    """
    if config.camera_index >= len(dataset.cameras):
        raise SpecError(f"train.camera_index {config.camera_index} is out of range: the dataset has cameras "
                        f"{dataset.cameras}")
    shortest = min(dataset.episode_length(i) for i in dataset.episodes("train"))
    if shortest < min_length:
        raise SpecError(f"this encoder's training samples need episodes of at least {min_length} frames; the "
                        f"shortest train episode has {shortest}")
    return run_training(net, dataset, config, budget, progress, workdir, seed=seed, batch_loss=batch_loss)
