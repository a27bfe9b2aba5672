"""Constructing a registered encoder, untrained, and reading the frozen base it declares.

The run's plan (`run.plan`) constructs one to ask what the run needs; the artifacts (`run.artifacts`) construct
one when no planned encoder is handed to them; the conformance check and the performance suite construct
their own.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from mftcn_bench.core import registry
from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.specs import encoder_spec_from_config
from mftcn_bench.encoders.base import Encoder, FeatureCacheUser, FrozenFrameBase


def construct_encoder(entry: registry.Entry, encoder_config: Mapping[str, Any], seed: int,
                      image_shape: tuple[int, int]) -> Encoder:
    """An encoder, constructed (untrained) for frames of `image_shape` (height, width)."""
    spec = encoder_spec_from_config(entry.description, encoder_config)
    encoder = entry.load()(spec, image_shape=image_shape, seed=seed)
    if not isinstance(encoder, Encoder):
        raise BenchError(f"encoder {spec.name!r} ({entry.entry_point.value}) does not "
                         f"implement the Encoder protocol (info, needs_fit, fit, embed, save, load)")
    return encoder


def frozen_base_of(encoder: Encoder) -> FrozenFrameBase | None:
    """The encoder's frozen base when it declares one (the `FeatureCacheUser` capability); one that is no
    `FrozenFrameBase` is refused in one line."""
    base = encoder.frozen_base() if isinstance(encoder, FeatureCacheUser) else None
    if base is not None and not isinstance(base, FrozenFrameBase):
        raise BenchError(f"encoder {encoder.info.name!r}: frozen_base() returned a {type(base).__name__}, which is "
                         f"no FrozenFrameBase (identity() and a call on uint8 frames [B, 3, H, W]; "
                         f"mftcn_bench.encoders.base)")
    return base
