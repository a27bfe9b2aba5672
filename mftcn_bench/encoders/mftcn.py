"""Multi-frame Time-Contrastive Network (mfTCN): per-frame base, 3D convolution over the clip, spatial
average, fully connected layer to the embedding; trained multi-view with the n-pairs loss.

The base is a spec choice (`[model.base]`, see `bases.py`): by default ImageNet EfficientNet-Lite0, frozen,
as the TCN code's embedders sit on a frozen ImageNet base. A trainable per-frame adapter (3x3 convolution,
BatchNorm, ReLU; `adapter_channels`) reads the base's feature maps, then the 3D convolution's temporal
kernel spans exactly the clip's n frames (already taken at stride s), so the embedding of a clip is
`head(stack(f(I_{t-(n-1)s}), ..., f(I_t)))` with `f = adapter . base`: per-frame work is done once per frame
and shared by every clip that contains it (`embed_episode`, streaming).

With a frozen base the head trains on a per-frame feature cache (`feature_cache.py`, attached by the
runner through `use_feature_cache`) and never decodes a frame; `small-cnn` (or `finetune = true`) trains
base and head end to end on frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
from torch import nn

from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import FitBudget, FrozenFrameBase, ProgressFn
from mftcn_bench.encoders.bases import BaseConfig, FrozenBase, base_channels, build_base
from mftcn_bench.encoders.common import FrameHeadEncoder, check_image_shape, map_batches, parse_table, to_numpy
from mftcn_bench.encoders.feature_cache import FeatureCache, base_features
from mftcn_bench.encoders.streaming import StreamingEmbedder
from mftcn_bench.encoders.training import ContrastiveTrainConfig, train_multiview


def parse_base(encoder: str, table: Any) -> BaseConfig:
    """The `[model.base]` table -> BaseConfig (one-line errors naming the table)."""
    if not isinstance(table, dict):
        raise SpecError(f"encoder {encoder!r}: [model.base] must be a table")
    return parse_table(BaseConfig, encoder, "model.base", table)


T = TypeVar("T")


def parse_model_on_base(cls: type[T], encoder: str, table: dict[str, Any]) -> T:
    """A `[model]` table with a `[model.base]` sub-table -> `cls` (its `base` field a BaseConfig)."""
    table = dict(table)
    base = parse_base(encoder, table.pop("base", {}))
    return parse_table(cls, encoder, "model", {**table, "base": base})


@dataclass(frozen=True)
class MfTCNModelConfig:
    """The `[model]` table of an mfTCN spec."""

    base: BaseConfig
    adapter_channels: int
    temporal_channels: int
    # Candidates for the wide views (docs/ENCODERS.md); the defaults are the paper's head. The 3D
    # convolution's spatial kernel (odd): its reach on the base's map, one cell of which spans a third of a
    # metre of the scene at 160x160 against a metre at 96x48.
    temporal_kernel: int = 3
    # How the head pools the clip's map: "mean" (the paper's mfTCN) or "mean+softargmax" (beside the mean,
    # each channel's expected x and y under a softmax over the map, the original TCN's spatial softmax: where
    # things are, which a mean over a 10x10 map nearly discards).
    spatial_pool: str = "mean"

    @classmethod
    def from_table(cls, encoder: str, table: dict[str, Any]) -> MfTCNModelConfig:
        config = parse_model_on_base(cls, encoder, table)
        if config.adapter_channels < 0 or config.temporal_channels < 1:
            raise SpecError(f"encoder {encoder!r}: [model] adapter_channels must be >= 0 and temporal_channels "
                            f">= 1, got {config.adapter_channels} and {config.temporal_channels}")
        if config.temporal_kernel < 1 or config.temporal_kernel % 2 == 0:
            raise SpecError(f"encoder {encoder!r}: [model] temporal_kernel must be an odd number >= 1, got "
                            f"{config.temporal_kernel}")
        if config.spatial_pool not in POOLS:
            raise SpecError(f"encoder {encoder!r}: [model] spatial_pool must be one of {', '.join(POOLS)}, got "
                            f"{config.spatial_pool!r}")
        return config


POOLS = ("mean", "mean+softargmax")


def spatial_softargmax(maps: torch.Tensor) -> torch.Tensor:
    """[B, C, h, w] -> [B, 2C]: each channel's expected (x, y) in [-1, 1] under a softmax over its map."""
    b, c, h, w = maps.shape
    weights = torch.softmax(maps.reshape(b, c, h * w), dim=-1).reshape(b, c, h, w)
    xs = torch.linspace(-1.0, 1.0, w, device=maps.device, dtype=maps.dtype)
    ys = torch.linspace(-1.0, 1.0, h, device=maps.device, dtype=maps.dtype)
    return torch.cat([(weights.sum(2) * xs).sum(-1), (weights.sum(3) * ys).sum(-1)], dim=1)


def frame_adapter(in_channels: int, channels: list[int]) -> nn.Module:
    """Per-frame 3x3 convolutions with BatchNorm and ReLU on base features (none: identity)."""
    layers: list[nn.Module] = []
    for width in channels:
        layers += [nn.Conv2d(in_channels, width, 3, padding=1), nn.BatchNorm2d(width), nn.ReLU()]
        in_channels = width
    return nn.Sequential(*layers) if layers else nn.Identity()


class OnBaseNet(nn.Module):
    """A clip network split as base -> per-frame adapter -> head over the clip's per-frame features.

    Subclasses set `base`, `adapter` and implement `head`. `frame_features` (base then adapter) is what a
    streaming embedder keeps per frame; `head_on_base` reads cached base features."""

    base: nn.Module
    adapter: nn.Module

    def head(self, features: torch.Tensor) -> torch.Tensor:
        """Per-frame features of clips [B, n, C, h, w] -> embeddings [B, D]."""
        raise NotImplementedError

    def frame_features(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 [N, 3, H, W] -> per-frame features [N, C', h, w]."""
        return self.adapter(self.base(images))

    def head_on_base(self, features: torch.Tensor) -> torch.Tensor:
        """Base features of clips [B, n, C, h, w] -> embeddings [B, D]."""
        b, n = features.shape[:2]
        adapted = self.adapter(features.reshape(b * n, *features.shape[2:]))
        return self.head(adapted.reshape(b, n, *adapted.shape[1:]))

    def forward(self, clips: torch.Tensor) -> torch.Tensor:
        """uint8 clips [B, n, 3, H, W] -> embeddings [B, D]."""
        b, n = clips.shape[:2]
        features = self.base(clips.reshape(b * n, *clips.shape[2:]))
        return self.head_on_base(features.reshape(b, n, *features.shape[1:]))

    @property
    def frozen_base(self) -> FrozenBase | None:
        return self.base if isinstance(self.base, FrozenBase) else None


class MfTCNNet(OnBaseNet):
    """Clip [B, n, 3, H, W] -> embedding [B, D]."""

    def __init__(self, config: MfTCNModelConfig, frames: int, embedding_dim: int) -> None:
        super().__init__()
        self.frames = frames
        self.base = build_base(config.base)
        channels = base_channels(self.base)
        adapter = [config.adapter_channels] if config.adapter_channels else []
        self.adapter = frame_adapter(channels, adapter)
        k = config.temporal_kernel
        self.temporal = nn.Conv3d(config.adapter_channels or channels, config.temporal_channels,
                                  kernel_size=(frames, k, k), padding=(0, k // 2, k // 2))
        self.softargmax = config.spatial_pool == "mean+softargmax"
        pooled = config.temporal_channels * (3 if self.softargmax else 1)
        self.fc = nn.Linear(pooled, embedding_dim)

    def head(self, features: torch.Tensor) -> torch.Tensor:
        phi = torch.relu(self.temporal(features.transpose(1, 2)))  # [B, C', 1, h, w]
        pooled = phi.mean(dim=(2, 3, 4))
        if self.softargmax:
            pooled = torch.cat([pooled, spatial_softargmax(phi[:, :, 0])], dim=1)
        return self.fc(pooled)


class OnBaseEncoder(FrameHeadEncoder):
    """A `FrameHeadEncoder` whose `net` is an `OnBaseNet`: with a frozen base it reads an attached feature
    cache (`use_feature_cache`) in training and when embedding episodes whose frames it holds."""

    net: OnBaseNet

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        super().__init__(spec, image_shape, seed)
        self.feature_cache: FeatureCache | None = None

    def frozen_base(self) -> FrozenFrameBase | None:
        """The frozen base whose per-frame features can be cached, or None when the base trains."""
        return self.net.frozen_base

    def use_feature_cache(self, cache: FeatureCache) -> None:
        """Read base features from `cache` (built by the runner for this encoder's frozen base and dataset)."""
        self.feature_cache = cache

    def training_features(self) -> FeatureCache | None:
        """The feature cache the head trains on (None: train from frames)."""
        return self.feature_cache if self.frozen_base() is not None else None

    @torch.no_grad()
    def embed_episode(self, frames: np.ndarray, state: np.ndarray | None = None,
                      batch_size: int = 256) -> np.ndarray:
        """Embeddings of the clips ending at every frame of one view [T, H, W, 3]: base features from the
        cache when it holds these frames (else one base pass per frame), the adapter per frame, then the
        head over gathered features."""
        cached = None if self.feature_cache is None else self.feature_cache.lookup(frames)
        base = (base_features(self.net.base, frames, batch_size, self.device) if cached is None
                else np.array(cached))
        features = map_batches(lambda rows: self.net.adapter(rows.to(self.device)), torch.from_numpy(base),
                               batch_size)
        index = torch.from_numpy(clip_indices(np.arange(len(frames)), self.spec.frames, self.spec.stride))
        out = map_batches(lambda rows: self.net.head(features[rows.to(self.device)]), index, batch_size)
        return to_numpy(out)


class MfTCNEncoder(OnBaseEncoder):
    """The mfTCN family (mftcn1 ... mftcn29): clip shape and sizes from the spec."""

    needs_fit = True
    training_views = 2  # n-pairs across two cameras' views of the same moment (`MultiViewTrainer`)

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        super().__init__(spec, image_shape, seed)
        self.configure(spec)
        torch.manual_seed(seed)
        self.net = self.build_net().eval()

    def configure(self, spec: EncoderSpec) -> None:
        """Validate the spec and set `model_config` and `train_config` (a subclass reads its own tables)."""
        self.model_config = MfTCNModelConfig.from_table(spec.name, dict(spec.model))
        self.train_config = ContrastiveTrainConfig.from_table(spec.name, dict(spec.train))

    def build_net(self) -> OnBaseNet:
        """The network, built right after seeding torch with the encoder's seed."""
        return MfTCNNet(self.model_config, self.spec.frames, self.spec.embedding_dim)

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        check_image_shape(self.image_shape, dataset)
        return train_multiview(self.net, dataset, self.train_config, budget, progress, workdir,
                               frames=self.spec.frames, stride=self.spec.stride, seed=self.seed,
                               features=self.training_features(), device=self.device)

    def streaming(self, num_envs: int) -> StreamingEmbedder:
        """A streaming embedder over `num_envs` environments: one base and adapter pass per new frame,
        per-frame features of the lookback window kept in a ring buffer (see `streaming.py`)."""
        return StreamingEmbedder(self.net, self.spec.frames, self.spec.stride, num_envs, self.device)
