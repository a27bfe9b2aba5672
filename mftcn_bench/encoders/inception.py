"""ImageNet InceptionV3 up to Mixed_5d: the trunk the original TCN built on (the `inception-v3` base of
`bases.py`; the `inception` encoder is its spatially averaged features, `frozen_features.py`).

The modules are torchvision's `Inception3` from `Conv2d_1a_3x3` to `Mixed_5d` with exactly its names
and shapes (torchvision itself is not a dependency), so a torchvision `inception_v3` state_dict loads
with `strict=True` once filtered to those prefixes; the rest of the file (Mixed_6a on, AuxLogits, fc)
is ignored. The weights are torchvision's IMAGENET1K_V1 file (`inception_v3_google-0cc3c7bd.pth`, ported
from TensorFlow), named by the spec's `[model.base] weights`. torchvision's own module cannot be used: its
wheels fail to import beside this project's CPU build of torch ("operator torchvision::nms does not exist").

Preprocessing (in `bases.InceptionV3Base`): frames are resized (bilinear) to `input_size` squared.
torchvision normalises with the ImageNet mean and std and then, for these weights, `transform_input` maps
each channel back with x * (std / 0.5) + (mean - 0.5) / 0.5; composed, that is (x / 255 - 0.5) / 0.5,
which is `bases.to_unit_range`.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from mftcn_bench.core.errors import BenchError

WEIGHTS_FILE = "inception_v3_google-0cc3c7bd.pth"
PREFIXES = ("Conv2d_1a_3x3", "Conv2d_2a_3x3", "Conv2d_2b_3x3", "Conv2d_3b_1x1", "Conv2d_4a_3x3",
            "Mixed_5b", "Mixed_5c", "Mixed_5d")


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
                         f"encoder.model.base.weights must name torchvision's inception_v3 IMAGENET1K_V1 "
                         f"state_dict ({WEIGHTS_FILE})") from None


def weights_help() -> str:
    return (f"give the path of torchvision's inception_v3 IMAGENET1K_V1 state_dict ({WEIGHTS_FILE}, from "
            f"https://download.pytorch.org/models/{WEIGHTS_FILE}) as encoder.model.base.weights, e.g. save it as "
            f"~/.mftcn-bench/weights/{WEIGHTS_FILE} and run `mftcn-bench run --encoder inception --set "
            f"encoder.model.base.weights=~/.mftcn-bench/weights/{WEIGHTS_FILE}` (a time-contrastive encoder on "
            f"this base names the file in its spec's [model.base] table, a variant file that extends it: "
            f"docs/ENCODERS.md)")


def checked_weights_path(weights: str) -> Path:
    """The weights file named by `[model.base] weights`, or a one-line error saying where to get it."""
    if not weights:
        raise BenchError(f"the inception-v3 base needs ImageNet weights: {weights_help()}")
    path = Path(weights).expanduser()
    if not path.is_file():
        raise BenchError(f"inception-v3 weights file {path} not found; {weights_help()}")
    return path
