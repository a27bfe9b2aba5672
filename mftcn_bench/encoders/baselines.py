"""The paper's reference rows: random state (lower bound), true state (upper bound), raw pixels via a CNN.

- `RandomStateEncoder` (`random-state`): Gaussian noise of the state's size. Each clip's noise comes from
  a numpy Generator seeded by (seed, a hash of the clip's pixel bytes), so a clip always gets the same
  noise, whatever the batch it is in or the order of the batches: results are reproducible.
- `TrueStateEncoder` (`true-state`): the simulator state of the clip's last frame. A 4-column cartpole
  state (x, theta, x_dot, theta_dot) is mapped like the probe's targets, to (x, sin theta, cos theta,
  x_dot, theta_dot); any other state is returned as it is.
- `PixelsCNNEncoder` (`pixels-cnn`): the mfTCN base CNN on each frame of the clip, spatial average, the
  clip's n averaged feature vectors concatenated (oldest first), one linear layer to the embedding. There
  is no training signal outside control tasks, so it is not fitted: a randomly initialised network from
  the seed. A control task trains its torch module, `encoder.net` (uint8 clips [B, n, 3, H, W] ->
  [B, D]), jointly with the policy.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mftcn_bench.data.clips import clip_indices
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import ClipBatch, EncoderInfo, FitBudget, ProgressFn
from mftcn_bench.encoders.frame_cnn import CNNConfig, load_network, parse_table, save_network, to_images
from mftcn_bench.encoders.mftcn import BaseCNN
from mftcn_bench.errors import BenchError, SpecError
from mftcn_bench.specs import EncoderSpec
from mftcn_bench.tasks.probe import state_targets

CARTPOLE_STATE_COLUMNS = 4  # x, theta, x_dot, theta_dot: mapped to the probe's five targets


@dataclass(frozen=True)
class NoTrainConfig:
    """The `[train]` table of an encoder that is never fitted: `steps` is accepted (presets set it) and
    ignored."""

    steps: int = 0


def _save_small(path: Path, payload: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def _load_small(path: Path) -> dict:
    try:
        return torch.load(path, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - truncated or foreign file
        raise BenchError(f"encoder checkpoint {path} cannot be loaded ({type(exc).__name__}); "
                         f"delete it to build it again") from None


@dataclass(frozen=True)
class RandomStateModelConfig:
    """The `[model]` table of `random-state`."""

    std: float = 1.0

    def __post_init__(self) -> None:
        if not self.std > 0:
            raise SpecError(f"random-state [model]: std must be > 0, got {self.std}")


def clip_noise(clip: np.ndarray, seed: int, dim: int, std: float) -> np.ndarray:
    """float32 [dim] Gaussian noise that depends only on (seed, the clip's pixel bytes)."""
    digest = hashlib.blake2b(np.ascontiguousarray(clip).tobytes(), digest_size=8).digest()
    rng = np.random.default_rng([seed, int.from_bytes(digest, "little")])
    return (rng.standard_normal(dim) * std).astype(np.float32)


class RandomStateEncoder:
    """Noise of a fixed size: the lower bound (a policy or probe that sees nothing of the state)."""

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        self.model_config = parse_table(RandomStateModelConfig, spec.name, "model", spec.model)
        parse_table(NoTrainConfig, spec.name, "train", spec.train)
        self.spec, self.image_shape, self.seed = spec, tuple(image_shape), seed

    @property
    def info(self) -> EncoderInfo:
        return EncoderInfo(self.spec.name, self.spec.frames, self.spec.stride, self.image_shape,
                           self.spec.embedding_dim, 0)

    @property
    def needs_fit(self) -> bool:
        return False

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        return {"steps": 0.0}

    def embed(self, clips: ClipBatch) -> np.ndarray:
        dim, std = self.spec.embedding_dim, self.model_config.std
        out = [clip_noise(clip, self.seed, dim, std) for clip in clips.frames]
        return np.stack(out) if out else np.zeros((0, dim), np.float32)

    def save(self, path: Path) -> None:
        _save_small(path, {"seed": self.seed, "embedding_dim": self.spec.embedding_dim})

    def load(self, path: Path) -> None:
        state = _load_small(path)
        if int(state.get("embedding_dim", -1)) != self.spec.embedding_dim:
            raise SpecError(f"encoder checkpoint {path} is for embedding_dim {state.get('embedding_dim')}, "
                            f"not {self.spec.embedding_dim}")
        self.seed = int(state["seed"])


@dataclass(frozen=True)
class EmptyModelConfig:
    """A `[model]` table that must stay empty."""


def state_embedding(state: np.ndarray) -> np.ndarray:
    """Last-frame state [B, S] -> embedding: a cartpole state (S = 4) becomes the probe's five targets
    (x, sin theta, cos theta, x_dot, theta_dot); other states are unchanged."""
    if state.shape[1] == CARTPOLE_STATE_COLUMNS:
        return state_targets(state)
    return state


class TrueStateEncoder:
    """The simulator's state as the embedding: the upper bound."""

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        parse_table(EmptyModelConfig, spec.name, "model", spec.model)
        parse_table(NoTrainConfig, spec.name, "train", spec.train)
        self.spec, self.image_shape, self.seed = spec, tuple(image_shape), seed

    @property
    def info(self) -> EncoderInfo:
        return EncoderInfo(self.spec.name, self.spec.frames, self.spec.stride, self.image_shape,
                           self.spec.embedding_dim, 0)

    @property
    def needs_fit(self) -> bool:
        return False

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        return {"steps": 0.0}

    def embed(self, clips: ClipBatch) -> np.ndarray:
        if clips.state is None:
            raise BenchError(f"{self.spec.name} needs the simulator state; this task's clips have none "
                             f"(ClipBatch.state is None)")
        state = np.asarray(clips.state)
        if state.ndim != 3:
            raise BenchError(f"{self.spec.name} expects clip states [B, n, S], got shape {state.shape}")
        out = state_embedding(state[:, -1].astype(np.float64)).astype(np.float32)
        if out.shape[1] != self.spec.embedding_dim:
            raise SpecError(f"{self.spec.name}: the task's state gives {out.shape[1]} values per frame but "
                            f"embedding_dim is {self.spec.embedding_dim}; set encoder.embedding_dim="
                            f"{out.shape[1]}")
        return out

    def save(self, path: Path) -> None:
        _save_small(path, {"embedding_dim": self.spec.embedding_dim})

    def load(self, path: Path) -> None:
        _load_small(path)


class PixelsCNNNet(nn.Module):
    """uint8 clips [B, n, 3, H, W] -> [B, D]: per-frame BaseCNN and spatial average, the n feature
    vectors concatenated, one linear layer."""

    def __init__(self, config: CNNConfig, frames: int, embedding_dim: int) -> None:
        super().__init__()
        self.base = BaseCNN(config.base_config())
        self.fc = nn.Linear(frames * self.base.out_channels, embedding_dim)

    def frame_features(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 [N, 3, H, W] -> spatially averaged features [N, C]."""
        return self.base(images).mean(dim=(2, 3))

    def head(self, features: torch.Tensor) -> torch.Tensor:
        """Pooled features of clips [B, n, C] -> embeddings [B, D]."""
        return self.fc(features.flatten(1))

    def forward(self, clips: torch.Tensor) -> torch.Tensor:
        b, n = clips.shape[:2]
        features = self.frame_features(clips.reshape(b * n, *clips.shape[2:]))
        return self.head(features.reshape(b, n, -1))


class PixelsCNNEncoder:
    """Raw pixels through a CNN: untrained (seeded random weights) unless a control task trains `net`."""

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        self.model_config = parse_table(CNNConfig, spec.name, "model", spec.model)
        parse_table(NoTrainConfig, spec.name, "train", spec.train)
        self.spec, self.image_shape, self.seed = spec, tuple(image_shape), seed
        torch.manual_seed(seed)
        self.net = PixelsCNNNet(self.model_config, spec.frames, spec.embedding_dim).eval()

    @property
    def info(self) -> EncoderInfo:
        return EncoderInfo(self.spec.name, self.spec.frames, self.spec.stride, self.image_shape,
                           self.spec.embedding_dim, sum(p.numel() for p in self.net.parameters()))

    @property
    def needs_fit(self) -> bool:
        return False

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        return {"steps": 0.0}

    @torch.no_grad()
    def embed(self, clips: ClipBatch) -> np.ndarray:
        return self.net(to_images(clips.frames)).numpy().astype(np.float32, copy=False)

    @torch.no_grad()
    def embed_episode(self, frames: np.ndarray, state: np.ndarray | None = None,
                      batch_size: int = 256) -> np.ndarray:
        """Embeddings of the clips ending at every frame of one view [T, H, W, 3], one CNN pass a frame."""
        images = to_images(frames)
        features = torch.cat([self.net.frame_features(images[i:i + batch_size])
                              for i in range(0, len(images), batch_size)])
        index = torch.from_numpy(clip_indices(np.arange(len(frames)), self.spec.frames, self.spec.stride))
        return self.net.head(features[index]).numpy().astype(np.float32, copy=False)

    def save(self, path: Path) -> None:
        save_network(path, self.net, self.image_shape)

    def load(self, path: Path) -> None:
        load_network(path, self.net, self.image_shape)
