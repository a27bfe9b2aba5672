"""Single-frame Time-Contrastive Network (TCN, Sermanet et al.) as the TCN code builds it: a base (by
default the same frozen ImageNet EfficientNet-Lite0 as mfTCN, `[model.base]`), trainable 3x3 convolutions
with BatchNorm and ReLU (`conv_channels`; the code's `additional_conv_sizes`), a spatial soft-argmax, fully
connected layers (`hidden`; the code's `fc_hidden_sizes`) and a linear layer to the embedding. TCN and
mfTCN differ where the paper says: one frame and a soft-argmax against a 3D convolution over n frames and
a spatial average.

The spatial soft-argmax turns each feature map into the expected image position of its activation: a
softmax over the map's H*W positions (features divided by a temperature, learned by default as in
TensorFlow's `spatial_softmax`), then the expected x and y coordinates in [-1, 1] under that
distribution, 2 numbers per channel, interleaved (x_0, y_0, x_1, y_1, ...).

Training, chosen by `[train] loss`:

- `"npairs"` (default): multi-view n-pairs, exactly as mfTCN (`train_multiview` with one frame a clip).
- `"triplet"`: the single-view TCN. Each triplet is one view of one episode: an anchor frame, a positive
  within `positive_radius` frames of it (not itself) and a negative more than `negative_margin` frames
  away; loss max(0, |a - p|^2 - |a - n|^2 + margin) on L2-normalised embeddings (the margin is on the
  unit sphere, as FaceNet and TensorFlow's triplet losses expect), so in this mode the network's output
  is L2-normalised at inference too. `batch_timesteps` is the number of triplets a batch;
  `alpha` and `reg_lambda` are used by n-pairs only.

The encoder reuses mfTCN's construction, embedding, feature cache, checkpoint and streaming code
(`MfTCNEncoder`, with its own `configure` / `build_net`): the network is an `OnBaseNet` whose head reads
the clip's single frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mftcn_bench.core.errors import DataError, SpecError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import FitBudget, ProgressFn
from mftcn_bench.encoders.bases import BaseConfig, base_channels, build_base
from mftcn_bench.encoders.common import check_image_shape
from mftcn_bench.encoders.feature_cache import FeatureCache
from mftcn_bench.encoders.mftcn import MfTCNEncoder, OnBaseNet, frame_adapter, parse_model_on_base
from mftcn_bench.encoders.training import (
    ContrastiveTrainConfig,
    EpisodePool,
    run_training,
    views_of,
)

LOSSES = ("npairs", "triplet")


@dataclass(frozen=True)
class TCNModelConfig:
    """The `[model]` table of a TCN spec."""

    base: BaseConfig
    conv_channels: list[int] = field(default_factory=list)  # trainable 3x3 conv + BN + ReLU layers on the base
    hidden: list[int] = field(default_factory=list)  # widths of ReLU layers between soft-argmax and output
    temperature: float = 1.0
    learn_temperature: bool = True

    def __post_init__(self) -> None:
        if not self.temperature > 0:
            raise SpecError(f"TCN [model]: temperature must be > 0, got {self.temperature}")
        if any(int(width) < 1 for width in [*self.hidden, *self.conv_channels]):
            raise SpecError(f"TCN [model]: hidden and conv_channels widths must be >= 1, got {self.hidden} and "
                            f"{self.conv_channels}")

    @classmethod
    def from_table(cls, encoder: str, table: dict[str, Any]) -> TCNModelConfig:
        return parse_model_on_base(cls, encoder, table)


@dataclass(frozen=True)
class TCNTrainConfig:
    """The `[train]` table of a TCN spec: the shared contrastive settings plus the loss choice and the
    single-view triplet's sampling radii and margin."""

    base: ContrastiveTrainConfig
    loss: str = "npairs"
    positive_radius: int = 6
    negative_margin: int = 12
    margin: float = 0.2

    OWN_KEYS = ("loss", "positive_radius", "negative_margin", "margin")

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise SpecError(f"TCN [train]: loss must be one of {', '.join(LOSSES)}; got {self.loss!r}")
        if self.positive_radius < 1:
            raise SpecError(f"TCN [train]: positive_radius must be >= 1, got {self.positive_radius}")
        if self.negative_margin < self.positive_radius:
            raise SpecError(f"TCN [train]: negative_margin ({self.negative_margin}) must be >= "
                            f"positive_radius ({self.positive_radius})")
        if self.margin < 0:
            raise SpecError(f"TCN [train]: margin must be >= 0, got {self.margin}")

    @classmethod
    def from_table(cls, name: str, table: dict[str, Any]) -> TCNTrainConfig:
        table = dict(table)
        own = {key: table.pop(key) for key in cls.OWN_KEYS if key in table}
        return cls(ContrastiveTrainConfig.from_table(name, table), **own)


def _axis(size: int, like: torch.Tensor) -> torch.Tensor:
    """Pixel-centre coordinates from -1 to 1 along an axis of `size` positions (0 if just one)."""
    if size == 1:
        return torch.zeros(1, dtype=like.dtype, device=like.device)
    return torch.linspace(-1.0, 1.0, size, dtype=like.dtype, device=like.device)


def spatial_soft_argmax(features: torch.Tensor, temperature: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Features [N, C, H, W] -> expected (x, y) per channel [N, 2C], interleaved x_0, y_0, x_1, ...

    For each channel: softmax of features / temperature over its H*W positions, then the expected
    x and y coordinates, x from -1 (left column) to 1 (right), y from -1 (top row) to 1 (bottom);
    an axis of one position has coordinate 0.
    """
    n, c, h, w = features.shape
    probs = F.softmax(features.reshape(n, c, h * w) / temperature, dim=-1).reshape(n, c, h, w)
    xs, ys = _axis(w, features), _axis(h, features)
    expected_x = (probs.sum(dim=2) * xs).sum(dim=-1)  # marginal over rows, then E[x]
    expected_y = (probs.sum(dim=3) * ys).sum(dim=-1)
    return torch.stack([expected_x, expected_y], dim=-1).reshape(n, 2 * c)


class SpatialSoftArgmax(nn.Module):
    """`spatial_soft_argmax` with a (by default learned) temperature."""

    def __init__(self, temperature: float, learn: bool) -> None:
        super().__init__()
        value = torch.tensor(float(temperature))
        if learn:
            self.temperature = nn.Parameter(value)
        else:
            self.register_buffer("temperature", value)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return spatial_soft_argmax(features, self.temperature)


class TCNNet(OnBaseNet):
    """One-frame clip [B, 1, 3, H, W] (uint8) -> embedding [B, D]."""

    def __init__(self, config: TCNModelConfig, embedding_dim: int, l2_normalize: bool = False) -> None:
        super().__init__()
        self.l2_normalize = l2_normalize
        self.base = build_base(config.base)
        channels = base_channels(self.base)
        self.adapter = frame_adapter(channels, [int(c) for c in config.conv_channels])
        self.keypoints = SpatialSoftArgmax(config.temperature, config.learn_temperature)
        layers: list[nn.Module] = []
        previous = 2 * (int(config.conv_channels[-1]) if config.conv_channels else channels)
        for width in config.hidden:
            layers += [nn.Linear(previous, int(width)), nn.ReLU()]
            previous = int(width)
        layers.append(nn.Linear(previous, embedding_dim))
        self.fc = nn.Sequential(*layers)

    def head(self, features: torch.Tensor) -> torch.Tensor:
        """Per-frame features of one-frame clips [B, 1, C, h, w] -> embeddings [B, D]."""
        out = self.fc(self.keypoints(features[:, -1]))
        return F.normalize(out, dim=1) if self.l2_normalize else out


def triplet_loss(anchors: torch.Tensor, positives: torch.Tensor, negatives: torch.Tensor,
                 margin: float) -> torch.Tensor:
    """mean max(0, |a - p|^2 - |a - n|^2 + margin) over rows of [K, D] embeddings."""
    close = (anchors - positives).pow(2).sum(1)
    far = (anchors - negatives).pow(2).sum(1)
    return F.relu(close - far + margin).mean()


@dataclass(frozen=True)
class TripletPlan:
    """Which frames make up one single-view triplet batch; all three of a row share episode and view."""

    episodes: np.ndarray  # [K]
    views: np.ndarray  # [K]
    anchors: np.ndarray  # [K] time steps
    positives: np.ndarray  # [K], 0 < |positive - anchor| <= positive_radius
    negatives: np.ndarray  # [K], |negative - anchor| > negative_margin


def sample_triplets(rng: np.random.Generator, episodes: list[int], lengths: dict[int, int], views: int,
                    count: int, episodes_per_batch: int, positive_radius: int,
                    negative_margin: int) -> TripletPlan:
    """`count` triplets split as evenly as possible over `episodes_per_batch` distinct episodes; each
    takes a random view, an anchor uniform among the frames that have a negative, then a positive and a
    negative uniform among the frames that qualify."""
    per_batch = min(episodes_per_batch, len(episodes), count)
    picked = rng.choice(episodes, size=per_batch, replace=False)
    counts = np.full(per_batch, count // per_batch)
    counts[: count % per_batch] += 1
    rows: list[tuple[int, int, int, int, int]] = []
    for episode, k in zip(picked, counts, strict=True):
        length = lengths[int(episode)]
        if length < negative_margin + 2:
            raise DataError(f"an episode of {length} frames has no frame more than {negative_margin} "
                            f"frames from another; use longer episodes or a smaller train.negative_margin")
        times = np.arange(length)
        anchors = times[(times > negative_margin) | (times < length - 1 - negative_margin)]
        for _ in range(int(k)):
            anchor = int(rng.choice(anchors))
            distance = np.abs(times - anchor)
            positive = int(rng.choice(times[(distance >= 1) & (distance <= positive_radius)]))
            negative = int(rng.choice(times[distance > negative_margin]))
            rows.append((int(episode), int(rng.integers(views)), anchor, positive, negative))
    columns = np.array(rows, dtype=np.int64).T
    return TripletPlan(*columns)


def gather_triplets(pool: EpisodePool, plan: TripletPlan, frames: int, stride: int) -> np.ndarray:
    """[3, K, n, ...]: anchor, positive and negative clips of each planned triplet (uint8 frames, or base
    features for a pool of cached features)."""
    out = []
    for times in (plan.anchors, plan.positives, plan.negatives):
        index = clip_indices(times, frames, stride)
        out.append(np.stack([views_of(pool.episodes[int(e)])[int(v), idx]
                             for e, v, idx in zip(plan.episodes, plan.views, index, strict=True)]))
    return np.stack(out)


def train_triplet(net: OnBaseNet, dataset: MultiViewDataset, config: TCNTrainConfig, budget: FitBudget,
                  progress: ProgressFn, workdir: Path, *, frames: int, stride: int,
                  seed: int, features: FeatureCache | None = None,
                  device: torch.device | None = None) -> dict[str, float]:
    """Train `net` with the single-view triplet loss; returns {'final_loss', 'steps', 'seconds'}.

    Same pool, optimizer and checkpoint/resume scheme as `train_multiview`; with `features`, on cached base
    features."""
    base = config.base
    shortest = min(dataset.episode_length(i) for i in dataset.episodes("train"))
    if shortest < config.negative_margin + 2:
        raise SpecError(f"train.negative_margin of {config.negative_margin} frames needs episodes of at least "
                        f"{config.negative_margin + 2} frames; the shortest train episode has {shortest}")
    views = len(dataset.cameras)
    target = device or torch.device("cpu")

    def embed(batch: np.ndarray) -> torch.Tensor:
        if features is None:
            return net(torch.from_numpy(batch).to(target).permute(0, 1, 4, 2, 3))
        return net.head_on_base(torch.from_numpy(batch).to(target))

    def batch_loss(pool: EpisodePool, rng: np.random.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        lengths = {i: pool.length(i) for i in pool.episodes}
        plan = sample_triplets(rng, sorted(pool.episodes), lengths, views, base.batch_timesteps,
                               base.episodes_per_batch, config.positive_radius, config.negative_margin)
        clips = gather_triplets(pool, plan, frames, stride)
        count = clips.shape[1]
        anchors, positives, negatives = embed(clips.reshape(3 * count, *clips.shape[2:])).reshape(3, count, -1)
        return triplet_loss(anchors, positives, negatives, config.margin), {}

    return run_training(net, dataset, base, budget, progress, workdir, seed=seed, batch_loss=batch_loss,
                        load=None if features is None else features.load, device=device)


class TCNEncoder(MfTCNEncoder):
    """The single-frame TCN: embedding, checkpoints and streaming as mfTCN, its own network and losses."""

    def configure(self, spec: EncoderSpec) -> None:
        if spec.frames != 1:
            raise SpecError(f"encoder {spec.name!r} is single-frame TCN: frames must be 1, got {spec.frames}")
        self.model_config = TCNModelConfig.from_table(spec.name, dict(spec.model))
        self.tcn_train_config = TCNTrainConfig.from_table(spec.name, dict(spec.train))
        self.train_config = self.tcn_train_config.base

    def build_net(self) -> OnBaseNet:
        triplet = self.tcn_train_config.loss == "triplet"
        return TCNNet(self.model_config, self.spec.embedding_dim, l2_normalize=triplet)

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        if self.tcn_train_config.loss != "triplet":
            return super().fit(dataset, budget, progress, workdir)
        check_image_shape(self.image_shape, dataset)
        return train_triplet(self.net, dataset, self.tcn_train_config, budget, progress, workdir,
                             frames=self.spec.frames, stride=self.spec.stride, seed=self.seed,
                             features=self.training_features(), device=self.device)
