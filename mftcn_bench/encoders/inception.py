"""ImageNet InceptionV3 features up to Mixed_5d, spatially averaged: a frozen 288-dimensional encoder
(the trunk the original TCN built on).

The modules are torchvision's `Inception3` from `Conv2d_1a_3x3` to `Mixed_5d` with exactly its names
and shapes (torchvision itself is not a dependency), so a torchvision `inception_v3` state_dict loads
with `strict=True` once filtered to those prefixes; the rest of the file (Mixed_6a on, AuxLogits, fc)
is ignored. The weights are torchvision's IMAGENET1K_V1 file (`inception_v3_google-0cc3c7bd.pth`, ported
from TensorFlow), named by the spec's `[model] weights`.

Preprocessing: frames are resized (bilinear) to `input_size` squared. torchvision normalises with the
ImageNet mean and std and then, for these weights, `transform_input` maps each channel back with
x * (std / 0.5) + (mean - 0.5) / 0.5; composed, that is (x / 255 - 0.5) / 0.5, which is `to_unit_range`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mftcn_bench.encoders.base import ClipBatch
from mftcn_bench.encoders.common import SpecEncoder, map_batches, parse_table, save_payload, to_images
from mftcn_bench.encoders.mftcn import to_unit_range
from mftcn_bench.errors import BenchError, SpecError
from mftcn_bench.specs import EncoderSpec

WEIGHTS_FILE = "inception_v3_google-0cc3c7bd.pth"
FEATURE_DIM = 288
PREFIXES = ("Conv2d_1a_3x3", "Conv2d_2a_3x3", "Conv2d_2b_3x3", "Conv2d_3b_1x1", "Conv2d_4a_3x3",
            "Mixed_5b", "Mixed_5c", "Mixed_5d")


@dataclass(frozen=True)
class InceptionModelConfig:
    """The `[model]` table of the inception spec."""

    weights: str = ""
    input_size: int = 299
    batch_size: int = 32  # frames a forward pass when embedding

    def __post_init__(self) -> None:
        if self.input_size < 75:
            raise SpecError(f"inception [model]: input_size must be >= 75 (InceptionV3's smallest input), "
                            f"got {self.input_size}")
        if self.batch_size < 1:
            raise SpecError(f"inception [model]: batch_size must be >= 1, got {self.batch_size}")


class BasicConv2d(nn.Module):
    """torchvision's BasicConv2d: convolution without bias, BatchNorm (eps 0.001), ReLU."""

    def __init__(self, in_channels: int, out_channels: int, **kwargs: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, bias=False, **kwargs)
        self.bn = nn.BatchNorm2d(out_channels, eps=0.001)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn(self.conv(x)), inplace=True)


class InceptionA(nn.Module):
    """torchvision's InceptionA block: 1x1, 5x5, double 3x3 and pooled branches, concatenated."""

    def __init__(self, in_channels: int, pool_features: int) -> None:
        super().__init__()
        self.branch1x1 = BasicConv2d(in_channels, 64, kernel_size=1)
        self.branch5x5_1 = BasicConv2d(in_channels, 48, kernel_size=1)
        self.branch5x5_2 = BasicConv2d(48, 64, kernel_size=5, padding=2)
        self.branch3x3dbl_1 = BasicConv2d(in_channels, 64, kernel_size=1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, kernel_size=3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, kernel_size=3, padding=1)
        self.branch_pool = BasicConv2d(in_channels, pool_features, kernel_size=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        branch1x1 = self.branch1x1(x)
        branch5x5 = self.branch5x5_2(self.branch5x5_1(x))
        branch3x3dbl = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        branch_pool = self.branch_pool(F.avg_pool2d(x, kernel_size=3, stride=1, padding=1))
        return torch.cat([branch1x1, branch5x5, branch3x3dbl, branch_pool], 1)


class InceptionV3ToMixed5d(nn.Module):
    """torchvision's Inception3 from the input to Mixed_5d: images in [-1, 1] [N, 3, S, S] -> [N, 288, s, s]
    (s = 35 at S = 299)."""

    def __init__(self) -> None:
        super().__init__()
        self.Conv2d_1a_3x3 = BasicConv2d(3, 32, kernel_size=3, stride=2)
        self.Conv2d_2a_3x3 = BasicConv2d(32, 32, kernel_size=3)
        self.Conv2d_2b_3x3 = BasicConv2d(32, 64, kernel_size=3, padding=1)
        self.maxpool1 = nn.MaxPool2d(kernel_size=3, stride=2)
        self.Conv2d_3b_1x1 = BasicConv2d(64, 80, kernel_size=1)
        self.Conv2d_4a_3x3 = BasicConv2d(80, 192, kernel_size=3)
        self.maxpool2 = nn.MaxPool2d(kernel_size=3, stride=2)
        self.Mixed_5b = InceptionA(192, pool_features=32)
        self.Mixed_5c = InceptionA(256, pool_features=64)
        self.Mixed_5d = InceptionA(288, pool_features=64)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.maxpool1(self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x))))
        x = self.maxpool2(self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(x)))
        return self.Mixed_5d(self.Mixed_5c(self.Mixed_5b(x)))


def load_torchvision_weights(module: InceptionV3ToMixed5d, path: Path) -> None:
    """Load the Conv2d_1a_3x3 ... Mixed_5d entries of a torchvision inception_v3 state_dict (strict)."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict):
            raise TypeError(f"a {type(state).__name__}, not a state_dict")
        kept = {k: v for k, v in state.items() if k.split(".", 1)[0] in PREFIXES}
        module.load_state_dict(kept, strict=True)
    except Exception as exc:  # noqa: BLE001 - truncated, foreign or mismatched file
        detail = " ".join(str(exc).split())[:200]
        raise BenchError(f"inception weights {path} cannot be loaded ({type(exc).__name__}: {detail}); "
                         f"encoder.model.weights must name torchvision's inception_v3 IMAGENET1K_V1 "
                         f"state_dict ({WEIGHTS_FILE})") from None


def _weights_help(name: str) -> str:
    return (f"give the path of torchvision's inception_v3 IMAGENET1K_V1 state_dict ({WEIGHTS_FILE}, from "
            f"https://download.pytorch.org/models/{WEIGHTS_FILE}) as the spec key encoder.model.weights, "
            f"e.g. save it as ~/.mftcn-bench/weights/{WEIGHTS_FILE} and run `mftcn-bench run --encoder {name} "
            f"--set encoder.model.weights=~/.mftcn-bench/weights/{WEIGHTS_FILE}`")


class InceptionEncoder(SpecEncoder):
    """Frozen ImageNet InceptionV3 Mixed_5d features, spatially averaged (one frame a clip)."""

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        super().__init__(spec, image_shape, seed)
        self.model_config = parse_table(InceptionModelConfig, spec.name, "model", spec.model)
        if spec.train:
            raise SpecError(f"encoder {spec.name!r} is not trained: its [train] table must be empty, "
                            f"got keys {sorted(spec.train)}")
        if spec.frames != 1 or spec.embedding_dim != FEATURE_DIM:
            raise SpecError(f"encoder {spec.name!r}: frames must be 1 and embedding_dim {FEATURE_DIM} "
                            f"(Mixed_5d's channels), got {spec.frames} and {spec.embedding_dim}")
        weights = self.model_config.weights
        if not weights:
            raise BenchError(f"encoder {spec.name!r} needs ImageNet weights: {_weights_help(spec.name)}")
        path = Path(weights).expanduser()
        if not path.is_file():
            raise BenchError(f"encoder {spec.name!r}: weights file {path} not found; {_weights_help(spec.name)}")
        self.net = InceptionV3ToMixed5d()
        load_torchvision_weights(self.net, path)
        self.net.eval().requires_grad_(False)

    def preprocess(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 [N, 3, H, W] -> float [N, 3, S, S] in [-1, 1], S = input_size."""
        size = self.model_config.input_size
        return F.interpolate(to_unit_range(images), size=(size, size), mode="bilinear", align_corners=False)

    @torch.no_grad()
    def features(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 [N, 3, H, W] -> spatially averaged Mixed_5d features [N, 288]."""
        if not len(images):
            return torch.zeros(0, FEATURE_DIM)
        return map_batches(lambda batch: self.net(self.preprocess(batch)).mean(dim=(2, 3)), images,
                           self.model_config.batch_size)

    def embed(self, clips: ClipBatch) -> np.ndarray:
        return self.features(to_images(clips.frames[:, -1])).numpy().astype(np.float32, copy=False)

    def embed_episode(self, frames: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """One forward pass per frame of one view [T, H, W, 3] -> [T, 288]."""
        return self.features(to_images(frames)).numpy().astype(np.float32, copy=False)

    def save(self, path: Path) -> None:
        save_payload(path, self.net.state_dict())

    def load(self, path: Path) -> None:
        load_torchvision_weights(self.net, path)
        self.net.eval()
