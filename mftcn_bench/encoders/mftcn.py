"""Multi-frame Time-Contrastive Network (mfTCN): per-frame CNN, 3D convolution over the clip, spatial
average, fully connected layer to the embedding; trained multi-view with the n-pairs loss.

The 3D convolution's temporal kernel spans exactly the clip's n frames (already taken at stride s), so
the embedding of a clip is `head(stack(base(I_{t-(n-1)s}), ..., base(I_t)))`: per-frame features are
computed once per frame and shared by every clip that contains it (`embed_episode`, from
`common.FrameHeadEncoder`).

The base CNN gets two extra input channels holding each pixel's normalised x and y coordinates
(CoordConv). The paper's spatial average otherwise discards where things are in the image, and the
cartpole's position is what a control policy needs most; the channels are a spec option (`coords`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import FitBudget, ProgressFn
from mftcn_bench.encoders.common import FrameHeadEncoder, check_image_shape, parse_table
from mftcn_bench.encoders.streaming import StreamingEmbedder
from mftcn_bench.encoders.training import ContrastiveTrainConfig, train_multiview
from mftcn_bench.errors import SpecError
from mftcn_bench.specs import EncoderSpec


@dataclass(frozen=True)
class MfTCNModelConfig:
    """The `[model]` table of an mfTCN spec."""

    channels: list[int]
    kernels: list[int]
    strides: list[int]
    temporal_channels: int
    coords: bool = True

    def __post_init__(self) -> None:
        if not (len(self.channels) == len(self.kernels) == len(self.strides) >= 1):
            raise SpecError("mfTCN [model]: channels, kernels and strides must be lists of one length")


def to_unit_range(frames: torch.Tensor) -> torch.Tensor:
    """uint8 [..., 3, H, W] -> float in [-1, 1]."""
    return frames.float().mul_(2.0 / 255.0).sub_(1.0)


class BaseCNN(nn.Module):
    """h_t = CNN(I_t): a stack of strided convolutions with ReLU."""

    def __init__(self, config: MfTCNModelConfig) -> None:
        super().__init__()
        self.coords = config.coords
        layers: list[nn.Module] = []
        previous = 3 + (2 if config.coords else 0)
        for channels, kernel, stride in zip(config.channels, config.kernels, config.strides, strict=True):
            layers += [nn.Conv2d(previous, channels, kernel, stride, padding=kernel // 2), nn.ReLU()]
            previous = channels
        self.layers = nn.Sequential(*layers)
        self.out_channels = previous

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 [N, 3, H, W] -> features [N, C, h, w]."""
        x = to_unit_range(images)
        if self.coords:
            n, _, h, w = x.shape
            ys = torch.linspace(-1.0, 1.0, h).view(1, 1, h, 1).expand(n, 1, h, w)
            xs = torch.linspace(-1.0, 1.0, w).view(1, 1, 1, w).expand(n, 1, h, w)
            x = torch.cat([x, xs, ys], dim=1)
        return self.layers(x)


class MfTCNNet(nn.Module):
    """Clip [B, n, 3, H, W] -> embedding [B, D]."""

    def __init__(self, config: MfTCNModelConfig, frames: int, embedding_dim: int) -> None:
        super().__init__()
        self.frames = frames
        self.base = BaseCNN(config)
        self.temporal = nn.Conv3d(self.base.out_channels, config.temporal_channels,
                                  kernel_size=(frames, 3, 3), padding=(0, 1, 1))
        self.fc = nn.Linear(config.temporal_channels, embedding_dim)

    def frame_features(self, images: torch.Tensor) -> torch.Tensor:
        return self.base(images)

    def head(self, features: torch.Tensor) -> torch.Tensor:
        """Per-frame features of clips [B, n, C, h, w] -> embeddings [B, D]."""
        phi = torch.relu(self.temporal(features.transpose(1, 2)))  # [B, C', 1, h, w]
        return self.fc(phi.mean(dim=(2, 3, 4)))

    def forward(self, clips: torch.Tensor) -> torch.Tensor:
        b, n = clips.shape[:2]
        features = self.frame_features(clips.reshape(b * n, *clips.shape[2:]))
        return self.head(features.reshape(b, n, *features.shape[1:]))


class MfTCNEncoder(FrameHeadEncoder):
    """The mfTCN family (mftcn1 ... mftcn29): clip shape and sizes from the spec."""

    needs_fit = True

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        super().__init__(spec, image_shape, seed)
        self.configure(spec)
        torch.manual_seed(seed)
        self.net = self.build_net().eval()

    def configure(self, spec: EncoderSpec) -> None:
        """Validate the spec and set `model_config` and `train_config` (a subclass reads its own tables)."""
        self.model_config = parse_table(MfTCNModelConfig, spec.name, "model", spec.model)
        self.train_config = ContrastiveTrainConfig.from_table(spec.name, dict(spec.train))

    def build_net(self) -> nn.Module:
        """The network, built right after seeding torch with the encoder's seed."""
        return MfTCNNet(self.model_config, self.spec.frames, self.spec.embedding_dim)

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        check_image_shape(self.image_shape, dataset)
        return train_multiview(self.net, dataset, self.train_config, budget, progress, workdir,
                               frames=self.spec.frames, stride=self.spec.stride, seed=self.seed)

    def streaming(self, num_envs: int) -> StreamingEmbedder:
        """A streaming embedder over `num_envs` environments: one base-CNN pass per new frame, per-frame
        features of the lookback window kept in a ring buffer (see `streaming.py`)."""
        return StreamingEmbedder(self.net, self.spec.frames, self.spec.stride, num_envs)
