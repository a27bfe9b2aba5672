"""Frame-CNN pieces shared by the single-frame encoders (pixels-cnn, PVE).

- `CNNConfig`: the convolution part of a `[model]` table (the mfTCN base CNN's layers).
- `FrameNet`: the from-scratch base CNN (`bases.SmallCNN`, with its optional coordinate channels), a spatial average
  and a linear layer: one uint8 frame -> a vector.
- `SingleViewTrainConfig` / `train_single_view`: Adam on a loss computed from a pool of decoded train
  episodes (the mfTCN trainer's `EpisodePool`), with the same atomic checkpoints and bitwise resume as
  `training.train_multiview`, and a NaN loss stopping with the step.

Table parsing, checkpoints and the encoder base class are in `common.py`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from mftcn_bench.core.errors import SpecError
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import FitBudget, ProgressFn
from mftcn_bench.encoders.bases import BaseConfig, SmallCNN
from mftcn_bench.encoders.training import BatchLoss, EpisodeLoader, run_training


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

    def base_config(self) -> BaseConfig:
        """The `small-cnn` base of these layers."""
        return BaseConfig(name="small-cnn", channels=list(self.channels), kernels=list(self.kernels),
                          strides=list(self.strides), coords=self.coords)


class FrameNet(nn.Module):
    """uint8 frames [N, 3, H, W] -> [N, out_dim]: SmallCNN, spatial average, linear layer."""

    def __init__(self, config: CNNConfig, out_dim: int) -> None:
        super().__init__()
        self.base = SmallCNN(config.base_config())
        self.fc = nn.Linear(self.base.out_channels, out_dim)

    def pooled(self, images: torch.Tensor) -> torch.Tensor:
        """Spatially averaged base-CNN features [N, C]."""
        return self.base(images).mean(dim=(2, 3))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.fc(self.pooled(images))


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
                      batch_loss: BatchLoss, load: EpisodeLoader | None = None,
                      device: torch.device | None = None) -> dict[str, float]:
    """Adam on `batch_loss` for `budget.steps` steps; returns {'final_loss', 'steps', 'seconds'}. The pool
    holds decoded episodes, or what `load` gives per episode (cached base features).

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
    return run_training(net, dataset, config, budget, progress, workdir, seed=seed, batch_loss=batch_loss,
                        load=load, device=device)
