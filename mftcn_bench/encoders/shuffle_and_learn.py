"""Shuffle and Learn (Misra et al. 2016): a siamese CNN learns whether three frames are in temporal order.

The trunk (the mfTCN base CNN, spatial average, linear layer to `embedding_dim`) is applied to each of
three frames; the three outputs are concatenated and a small MLP (one hidden ReLU layer of
`model.mlp_hidden`) gives one logit for "in temporal order". The embedding of a clip is the trunk's
output on its last frame (spec frames = 1).

Training uses one view (`train.camera_index`) of the train split. For each of `train.batch_size` draws,
five frames a < b < c < d < e of one episode are sampled, every gap between neighbours uniform in
[`min_spacing`, `max_spacing`] (capped so the five fit in the episode); the draw gives one positive,
(b, c, d), and one negative, (b, a, d) or (b, e, d) with equal chance, so batches are balanced. Loss:
binary cross-entropy on the logits; Adam.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mftcn_bench.core.errors import DataError, SpecError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import ClipBatch, FitBudget, ProgressFn
from mftcn_bench.encoders.common import SpecEncoder, check_image_shape, map_batches, parse_table, to_images
from mftcn_bench.encoders.frame_cnn import CNNConfig, FrameNet, SingleViewTrainConfig, train_single_view
from mftcn_bench.encoders.training import EpisodePool


@dataclass(frozen=True, kw_only=True)
class ShuffleModelConfig(CNNConfig):
    """The `[model]` table: the trunk's CNN and the order classifier's hidden width."""

    mlp_hidden: int

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.mlp_hidden < 1:
            raise SpecError(f"shuffle-and-learn [model]: mlp_hidden must be >= 1, got {self.mlp_hidden}")


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
    """`count` draws from episodes of the pool: (frames uint8 [2 count, 3, H, W, 3], labels [2 count],
    episode of each triplet [2 count], frame indices [2 count, 3])."""
    picked = rng.choice(sorted(pool.episodes), size=count)
    five = np.stack([sample_five(rng, pool.episodes[int(e)].length, min_spacing, max_spacing) for e in picked])
    times, labels = order_tuples(five, rng)
    episodes = np.concatenate([picked, picked])
    frames = np.stack([pool.episodes[int(e)].frames[camera, t] for e, t in zip(episodes, times, strict=True)])
    return frames, labels, episodes, times


class ShuffleNet(nn.Module):
    """A shared trunk on three frames and an MLP on the concatenated features: uint8 [N, 3, 3, H, W] ->
    order logits [N]."""

    def __init__(self, config: ShuffleModelConfig, embedding_dim: int) -> None:
        super().__init__()
        self.trunk = FrameNet(config, embedding_dim)
        self.classifier = nn.Sequential(nn.Linear(3 * embedding_dim, config.mlp_hidden), nn.ReLU(),
                                        nn.Linear(config.mlp_hidden, 1))

    def forward(self, triplets: torch.Tensor) -> torch.Tensor:
        n = triplets.shape[0]
        features = self.trunk(triplets.reshape(n * 3, *triplets.shape[2:])).reshape(n, -1)
        return self.classifier(features).squeeze(-1)


class ShuffleAndLearnEncoder(SpecEncoder):
    """Temporal-order verification; the trunk's output on the clip's frame is the embedding."""

    needs_fit = True

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        if spec.frames != 1:
            raise SpecError(f"encoder {spec.name!r}: Shuffle and Learn embeds one frame (frames = 1), "
                            f"got frames = {spec.frames}")
        super().__init__(spec, image_shape, seed)
        self.model_config = parse_table(ShuffleModelConfig, spec.name, "model", spec.model)
        self.train_config = parse_table(ShuffleTrainConfig, spec.name, "train", spec.train)
        torch.manual_seed(seed)
        self.net = ShuffleNet(self.model_config, spec.embedding_dim).eval()
        self.loss_fn = nn.BCEWithLogitsLoss()

    def counted_module(self) -> nn.Module:
        """Only the trunk embeds; the order classifier is a training device."""
        return self.net.trunk

    def batch_loss(self, pool: EpisodePool, rng: np.random.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        """BCE of the order classifier on one balanced batch, and its accuracy."""
        config = self.train_config
        frames, labels, _, _ = sample_order_batch(pool, rng, config.batch_size, config.camera_index,
                                                  config.min_spacing, config.max_spacing)
        logits = self.net(to_images(frames))
        target = torch.from_numpy(labels)
        accuracy = float(((logits.detach() > 0).float() == target).float().mean())
        return self.loss_fn(logits, target), {"accuracy": accuracy}

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        check_image_shape(self.image_shape, dataset)
        min_length = 4 * self.train_config.min_spacing + 1
        return train_single_view(self.net, dataset, self.train_config, budget, progress, workdir,
                                 seed=self.seed, min_length=min_length, batch_loss=self.batch_loss)

    @torch.no_grad()
    def embed(self, clips: ClipBatch) -> np.ndarray:
        return self.net.trunk(to_images(clips.frames[:, -1])).numpy().astype(np.float32, copy=False)

    @torch.no_grad()
    def embed_episode(self, frames: np.ndarray, state: np.ndarray | None = None,
                      batch_size: int = 256) -> np.ndarray:
        """The trunk's output for every frame of one view [T, H, W, 3]."""
        return map_batches(self.net.trunk, to_images(frames), batch_size).numpy().astype(np.float32, copy=False)
