"""The paper's reference rows: random state (lower bound), true state (upper bound), raw pixels via a CNN.

- `RandomStateEncoder` (`random-state`): Gaussian noise of the state's size. Each clip's noise comes from
  a numpy Generator seeded by (seed, a hash of the clip's pixel bytes), so a clip always gets the same
  noise, whatever the batch it is in, the order of the batches or whether it is embedded in a batch or in
  a rollout (its stream keeps the clip's frames): results are reproducible. Two cameras' views of one
  moment get unrelated noise (a hash of the shared state would make them align perfectly).
- `TrueStateEncoder` (`true-state`): the simulator state of the clip's last frame. A 4-column cartpole
  state (x, theta, x_dot, theta_dot) is mapped like the probe's targets, to (x, sin theta, cos theta,
  x_dot, theta_dot); any other state is returned as it is. `[model] noise_std` (one per embedding
  dimension; empty: none) adds Gaussian noise of that size, drawn from (seed, the state's bytes) so that
  `embed` and a rollout give a state the same noise: PPO on true state blurred to a given precision (for
  example a probe's residual) bounds what an embedding of that precision allows.
- `PixelsCNNEncoder` (`pixels-cnn`): the mfTCN base CNN on each frame of the clip, spatial average, the
  clip's n averaged feature vectors concatenated (oldest first), one linear layer to the embedding. There
  is no training signal outside control tasks, so it is not fitted: a randomly initialised network from
  the seed. A control task trains its torch module, `encoder.net` (uint8 clips [B, n, 3, H, W] ->
  [B, D]), jointly with the policy.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.cartpole import state_targets
from mftcn_bench.data.clips import ClipRing
from mftcn_bench.encoders.base import ClipBatch
from mftcn_bench.encoders.bases import SmallCNN
from mftcn_bench.encoders.common import FrameHeadEncoder, SpecEncoder, load_payload, parse_table, save_payload
from mftcn_bench.encoders.frame_cnn import CNNConfig

CARTPOLE_STATE_COLUMNS = 4  # x, theta, x_dot, theta_dot: mapped to the probe's five targets


@dataclass(frozen=True)
class NoTrainConfig:
    """The `[train]` table of an encoder that is never fitted: `steps` is accepted (presets set it) and
    ignored."""

    steps: int = 0


@dataclass(frozen=True)
class RandomStateModelConfig:
    """The `[model]` table of `random-state`."""

    std: float = 1.0

    def __post_init__(self) -> None:
        if not self.std > 0:
            raise SpecError(f"random-state [model]: std must be > 0, got {self.std}")


def clip_noise(clip: np.ndarray, seed: int, dim: int, std: float) -> np.ndarray:
    """float32 [dim] Gaussian noise that depends only on (seed, the clip's pixel bytes). Pixels, not the
    state: two cameras' views of one moment get unrelated noise (state-seeded noise would align them)."""
    digest = hashlib.blake2b(np.ascontiguousarray(clip).tobytes(), digest_size=8).digest()
    rng = np.random.default_rng([seed, int.from_bytes(digest, "little")])
    return (rng.standard_normal(dim) * std).astype(np.float32)


class RandomStateStream:
    """The noise of the clip ending at each environment's newest frame, exactly as `embed` draws it."""

    def __init__(self, seed: int, frames: int, stride: int, num_envs: int, dim: int, std: float) -> None:
        self.seed, self.dim, self.std = seed, dim, std
        self._clips = ClipRing(frames, stride, num_envs)

    def observe(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> None:
        self._clips.push(np.asarray(frames), episode_start)

    def push(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> np.ndarray:
        self.observe(frames, episode_start, state)
        return np.stack([clip_noise(clip, self.seed, self.dim, self.std) for clip in self._clips.clip()])


class RandomStateEncoder(SpecEncoder):
    """Noise of a fixed size: the lower bound (a policy or probe that sees nothing of the state)."""

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        super().__init__(spec, image_shape, seed)
        self.model_config = parse_table(RandomStateModelConfig, spec.name, "model", spec.model)
        parse_table(NoTrainConfig, spec.name, "train", spec.train)

    def embed(self, clips: ClipBatch) -> np.ndarray:
        dim, std = self.spec.embedding_dim, self.model_config.std
        out = [clip_noise(clip, self.seed, dim, std) for clip in clips.frames]
        return np.stack(out) if out else np.zeros((0, dim), np.float32)

    def streaming(self, num_envs: int) -> RandomStateStream:
        """Noise for rollouts: the same function of each clip's pixels as `embed` (rollouts render for it)."""
        return RandomStateStream(self.seed, self.spec.frames, self.spec.stride, num_envs, self.spec.embedding_dim,
                                 self.model_config.std)

    def save(self, path: Path) -> None:
        save_payload(path, {"seed": self.seed, "embedding_dim": self.spec.embedding_dim})

    def load(self, path: Path) -> None:
        state = load_payload(path)
        if int(state.get("embedding_dim", -1)) != self.spec.embedding_dim:
            raise SpecError(f"encoder checkpoint {path} is for embedding_dim {state.get('embedding_dim')}, "
                            f"not {self.spec.embedding_dim}")
        self.seed = int(state["seed"])


@dataclass(frozen=True)
class TrueStateModelConfig:
    """The `[model]` table of `true-state`: optional per-dimension noise."""

    noise_std: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        if any(not (np.isfinite(s) and s >= 0) for s in self.noise_std):
            raise SpecError(f"true-state [model]: noise_std must be finite numbers >= 0, got {self.noise_std}")


def state_noise(state: np.ndarray, seed: int, std: np.ndarray) -> np.ndarray:
    """float32 [B, D] Gaussian noise of per-dimension `std` [D] for states [B, S]: row b depends only on
    (seed, the bytes of state b as float64)."""
    rows = np.ascontiguousarray(np.asarray(state, dtype=np.float64))
    out = np.empty((len(rows), len(std)), np.float32)
    for i, row in enumerate(rows):
        digest = hashlib.blake2b(row.tobytes(), digest_size=8).digest()
        rng = np.random.default_rng([seed, int.from_bytes(digest, "little")])
        out[i] = rng.standard_normal(len(std)) * std
    return out


def state_embedding(state: np.ndarray) -> np.ndarray:
    """Last-frame state [B, S] -> embedding: a cartpole state (S = 4) becomes the probe's five targets
    (x, sin theta, cos theta, x_dot, theta_dot); other states are unchanged."""
    if state.shape[1] == CARTPOLE_STATE_COLUMNS:
        return state_targets(state)
    return state


class TrueStateEncoder(SpecEncoder):
    """The simulator's state as the embedding: the upper bound."""

    uses_pixels = False
    privileged_inputs = ("state",)

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        super().__init__(spec, image_shape, seed)
        config = parse_table(TrueStateModelConfig, spec.name, "model", spec.model)
        if config.noise_std and len(config.noise_std) != spec.embedding_dim:
            raise SpecError(f"encoder {spec.name!r}: [model] noise_std needs one value per embedding dimension "
                            f"({spec.embedding_dim}), got {len(config.noise_std)}")
        self.noise_std = np.asarray(config.noise_std, dtype=np.float64)
        parse_table(NoTrainConfig, spec.name, "train", spec.train)

    def embed(self, clips: ClipBatch) -> np.ndarray:
        if clips.state is None:
            raise BenchError(f"{self.spec.name} needs the simulator state; this task's clips have none "
                             f"(ClipBatch.state is None)")
        state = np.asarray(clips.state)
        if state.ndim != 3:
            raise BenchError(f"{self.spec.name} expects clip states [B, n, S], got shape {state.shape}")
        return self.embed_state(state[:, -1])

    def streaming(self, num_envs: int) -> TrueStateEncoder:
        """The state needs no history: the encoder itself serves rollouts (`push`)."""
        return self

    def push(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> np.ndarray:
        return self.embed_state(state)

    def embed_state(self, state: np.ndarray) -> np.ndarray:
        """States [B, S] -> float32 embeddings [B, D]."""
        out = state_embedding(np.asarray(state, dtype=np.float64)).astype(np.float32)
        if out.shape[1] != self.spec.embedding_dim:
            raise SpecError(f"{self.spec.name}: the task's state gives {out.shape[1]} values per frame but "
                            f"embedding_dim is {self.spec.embedding_dim}; set encoder.embedding_dim="
                            f"{out.shape[1]}")
        if self.noise_std.size:
            out += state_noise(state, self.seed, self.noise_std)
        return out

    def save(self, path: Path) -> None:
        save_payload(path, {"embedding_dim": self.spec.embedding_dim})

    def load(self, path: Path) -> None:
        load_payload(path)


class PixelsCNNNet(nn.Module):
    """uint8 clips [B, n, 3, H, W] -> [B, D]: per-frame SmallCNN and spatial average, the n feature
    vectors concatenated, one linear layer."""

    def __init__(self, config: CNNConfig, frames: int, embedding_dim: int) -> None:
        super().__init__()
        self.base = SmallCNN(config.base_config())
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


class PixelsCNNEncoder(FrameHeadEncoder):
    """Raw pixels through a CNN: untrained (seeded random weights) unless a control task trains `net`."""

    trains_with_policy = True  # control tasks feed it raw clips and train `net` with the policy

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        super().__init__(spec, image_shape, seed)
        self.model_config = parse_table(CNNConfig, spec.name, "model", spec.model)
        parse_table(NoTrainConfig, spec.name, "train", spec.train)
        torch.manual_seed(seed)
        self.net = PixelsCNNNet(self.model_config, spec.frames, spec.embedding_dim).eval()
