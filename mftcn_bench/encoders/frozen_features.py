"""A frozen base's features, spatially averaged, with no training: the reference that shows what
time-contrastive training of a head adds on the same base (and the paper's "Inception" pouring row, the
`inception` encoder on the `inception-v3` base).

The embedding of a clip is the mean over the feature map of its last frame: `embedding_dim` must equal
the base's channels. It reads the same per-frame feature cache as the heads on that base.
"""

from __future__ import annotations

import torch
from torch import nn

from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.encoders.bases import build_base
from mftcn_bench.encoders.mftcn import OnBaseEncoder, OnBaseNet, parse_base


class SpatialMeanNet(OnBaseNet):
    """A frozen base, then the spatial mean of the clip's last frame."""

    def __init__(self, base: nn.Module) -> None:
        super().__init__()
        self.base, self.adapter = base, nn.Identity()

    def head(self, features: torch.Tensor) -> torch.Tensor:
        return features[:, -1].mean(dim=(2, 3))


class FrozenFeaturesEncoder(OnBaseEncoder):
    """Spatially averaged features of a frozen pretrained base (`[model.base]`); nothing to train."""

    needs_fit = False

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        super().__init__(spec, image_shape, seed)
        unknown = sorted(set(spec.model) - {"base"})
        if unknown:
            raise SpecError(f"encoder {spec.name!r}: bad [model] table: unknown key(s) {unknown}; allowed: ['base']")
        if spec.train:
            raise SpecError(f"encoder {spec.name!r} is not trained: its [train] table must be empty, "
                            f"got keys {sorted(spec.train)}")
        config = parse_base(spec.name, spec.model.get("base", {}))
        if config.trains:
            raise SpecError(f"encoder {spec.name!r} needs a frozen pretrained base: [model.base] name must not be "
                            f"small-cnn and finetune must be false")
        channels = config.out_channels
        if spec.frames != 1 or spec.embedding_dim != channels:
            raise SpecError(f"encoder {spec.name!r}: frames must be 1 and embedding_dim {channels} (the "
                            f"{config.name} base's channels at this layer), got {spec.frames} and "
                            f"{spec.embedding_dim}")
        self.net = SpatialMeanNet(build_base(config)).eval()
