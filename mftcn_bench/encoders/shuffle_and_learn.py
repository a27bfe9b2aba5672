"""Shuffle and Learn (Misra et al. 2016): a siamese network learns whether three frames are in temporal order.

The trunk is an `OnBaseNet` on the same base as mfTCN and TCN (`[model.base]`, by default the frozen
ImageNet EfficientNet-Lite0, so training reads the per-frame feature cache): a per-frame adapter (3x3
convolution, BatchNorm, ReLU; `adapter_channels`), a spatial average and a linear layer to
`embedding_dim`. It is applied to each of three frames; the three outputs are concatenated and a small
MLP (one hidden ReLU layer of `mlp_hidden`) gives one logit for "in temporal order". The embedding of a
clip is the trunk's output on its last frame (spec frames = 1). `base.name = "small-cnn"` trains the
earlier from-scratch trunk end to end (its order classifier stayed at chance on cartpole: loss log 2).

Training uses one view (`train.camera_index`) of the train split. For each of `train.batch_size` draws,
five frames a < b < c < d < e of one episode are sampled, every gap between neighbours uniform in
[`min_spacing`, `max_spacing`] (capped so the five fit in the episode); the draw gives one positive,
(b, c, d), and one negative, (b, a, d) or (b, e, d) with equal chance, so batches are balanced. Loss:
binary cross-entropy on the logits; Adam. The classifier is a training device: it is not checkpointed
with the trunk and takes no part in embedding.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from mftcn_bench.core.errors import DataError, SpecError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import FitBudget, ProgressFn
from mftcn_bench.encoders.bases import BaseConfig, base_channels, build_base
from mftcn_bench.encoders.common import check_image_shape, parse_table, to_images
from mftcn_bench.encoders.frame_cnn import SingleViewTrainConfig, train_single_view
from mftcn_bench.encoders.mftcn import OnBaseEncoder, OnBaseNet, frame_adapter, parse_model_on_base
from mftcn_bench.encoders.streaming import StreamingEmbedder
from mftcn_bench.encoders.training import EpisodePool, views_of


@dataclass(frozen=True)
class ShuffleModelConfig:
    """The `[model]` table: the trunk's base and adapter, and the order classifier's hidden width."""

    base: BaseConfig
    adapter_channels: int
    mlp_hidden: int

    @classmethod
    def from_table(cls, encoder: str, table: dict[str, Any]) -> ShuffleModelConfig:
        config = parse_model_on_base(cls, encoder, table)
        if config.adapter_channels < 0 or config.mlp_hidden < 1:
            raise SpecError(f"encoder {encoder!r}: [model] adapter_channels must be >= 0 and mlp_hidden >= 1, "
                            f"got {config.adapter_channels} and {config.mlp_hidden}")
        return config


@dataclass(frozen=True, kw_only=True)
class ShuffleTrainConfig(SingleViewTrainConfig):
    """The `[train]` table: the common single-view keys plus the frame spacing of the 5-frame draws."""

    min_spacing: int
    max_spacing: int

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 1 <= self.min_spacing <= self.max_spacing:
            raise SpecError(f"shuffle-and-learn [train]: need 1 <= min_spacing <= max_spacing, got "
                            f"{self.min_spacing} and {self.max_spacing}")


def sample_five(rng: np.random.Generator, length: int, min_spacing: int, max_spacing: int) -> np.ndarray:
    """Sorted frame indices a < b < c < d < e in [0, length): gaps uniform in [min_spacing, max_spacing],
    the largest gap capped at (length - 1) // 4 so that the five always fit."""
    top = min(max_spacing, (length - 1) // 4)
    if top < min_spacing:
        raise DataError(f"an episode of {length} frames cannot hold 5 frames at least {min_spacing} apart; "
                        f"lower train.min_spacing or use longer episodes")
    gaps = rng.integers(min_spacing, top + 1, size=4)
    start = int(rng.integers(0, length - int(gaps.sum())))
    return start + np.concatenate([[0], np.cumsum(gaps)])


def order_tuples(five: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Five-frame draws [N, 5] -> triplets [2N, 3] and labels [2N] (1: in order): rows 0..N-1 are the
    positives (b, c, d), rows N..2N-1 the negatives (b, a, d) or (b, e, d)."""
    positives = five[:, [1, 2, 3]]
    outside = np.where(rng.random(len(five)) < 0.5, five[:, 0], five[:, 4])
    negatives = np.stack([five[:, 1], outside, five[:, 3]], axis=1)
    labels = np.concatenate([np.ones(len(five)), np.zeros(len(five))]).astype(np.float32)
    return np.concatenate([positives, negatives]), labels


def sample_order_batch(pool: EpisodePool, rng: np.random.Generator, count: int, camera: int, min_spacing: int,
                       max_spacing: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`count` draws from episodes of the pool: (per-frame items [2 count, 3, ...] — uint8 frames
    [H, W, 3] or cached base features [C, h, w] — labels [2 count], episode of each triplet [2 count],
    frame indices [2 count, 3])."""
    picked = rng.choice(sorted(pool.episodes), size=count)
    five = np.stack([sample_five(rng, pool.length(int(e)), min_spacing, max_spacing) for e in picked])
    times, labels = order_tuples(five, rng)
    episodes = np.concatenate([picked, picked])
    items = np.stack([views_of(pool.episodes[int(e)])[camera, t] for e, t in zip(episodes, times, strict=True)])
    return items, labels, episodes, times


class ShuffleTrunk(OnBaseNet):
    """One-frame clip [B, 1, 3, H, W] (uint8) -> embedding [B, D]: base, adapter, spatial mean, linear."""

    def __init__(self, config: ShuffleModelConfig, embedding_dim: int) -> None:
        super().__init__()
        self.base = build_base(config.base)
        channels = base_channels(self.base)
        self.adapter = frame_adapter(channels, [config.adapter_channels] if config.adapter_channels else [])
        self.fc = nn.Linear(config.adapter_channels or channels, embedding_dim)

    def head(self, features: torch.Tensor) -> torch.Tensor:
        return self.fc(features[:, -1].mean(dim=(2, 3)))


def order_classifier(embedding_dim: int, hidden: int) -> nn.Module:
    """Concatenated trunk outputs of a triplet [N, 3 D] -> order logit [N, 1]."""
    return nn.Sequential(nn.Linear(3 * embedding_dim, hidden), nn.ReLU(), nn.Linear(hidden, 1))


class ShuffleAndLearnEncoder(OnBaseEncoder):
    """Temporal-order verification; the trunk's output on the clip's frame is the embedding."""

    needs_fit = True
    net: ShuffleTrunk

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        if spec.frames != 1:
            raise SpecError(f"encoder {spec.name!r}: Shuffle and Learn embeds one frame (frames = 1), "
                            f"got frames = {spec.frames}")
        super().__init__(spec, image_shape, seed)
        self.model_config = ShuffleModelConfig.from_table(spec.name, dict(spec.model))
        self.train_config = parse_table(ShuffleTrainConfig, spec.name, "train", spec.train)
        torch.manual_seed(seed)
        self.net = ShuffleTrunk(self.model_config, spec.embedding_dim).eval()
        self.classifier = order_classifier(spec.embedding_dim, self.model_config.mlp_hidden)
        self.loss_fn = nn.BCEWithLogitsLoss()

    def batch_loss(self, pool: EpisodePool, rng: np.random.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        """BCE of the order classifier on one balanced batch, and its accuracy."""
        config = self.train_config
        items, labels, _, _ = sample_order_batch(pool, rng, config.batch_size, config.camera_index,
                                                 config.min_spacing, config.max_spacing)
        count = items.shape[0]
        single = items.reshape(count * 3, 1, *items.shape[2:])
        if self.training_features() is None:
            trunk = self.net(to_images(single).to(self.device))
        else:
            trunk = self.net.head_on_base(torch.from_numpy(np.ascontiguousarray(single)).to(self.device))
        logits = self.classifier(trunk.reshape(count, -1)).squeeze(-1)
        target = torch.from_numpy(labels).to(self.device)
        accuracy = float(((logits.detach() > 0).float() == target).float().mean())
        return self.loss_fn(logits, target), {"accuracy": accuracy}

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        check_image_shape(self.image_shape, dataset)
        min_length = 4 * self.train_config.min_spacing + 1
        cache = self.training_features()
        trained = nn.ModuleDict({"trunk": self.net, "classifier": self.classifier})
        return train_single_view(trained, dataset, self.train_config, budget, progress, workdir,
                                 seed=self.seed, min_length=min_length, batch_loss=self.batch_loss,
                                 load=None if cache is None else cache.load, device=self.device)

    def to_device(self, device: torch.device) -> None:
        """The trunk and the order classifier move to `device`."""
        super().to_device(device)
        self.classifier.to(self.device)

    def streaming(self, num_envs: int) -> StreamingEmbedder:
        """One base and adapter pass per new frame, then the trunk's head."""
        return StreamingEmbedder(self.net, 1, 1, num_envs, self.device)
