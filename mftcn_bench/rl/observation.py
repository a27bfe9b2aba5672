"""What the policy sees, as torchrl transforms over `SuiteBatchEnv`'s stream of frames and states.

`SuiteBatchEnv` simulates and renders the last k frames of the encoder's stream in each agent step; the
transforms turn them into the policy's input, the shape torchrl users know (`TransformedEnv`):

- `EncoderEmbedding`: the frozen encoder's embedding of the clip ending at the step's last frame (an
  observer, `observers.py`: the encoder's streaming embedder, or a clip window over its `embed`); the earlier
  frames only enter the clip history. With `difference` the observation is [e_t, e_t - e_{t-1}], e_{t-1}
  the embedding of the stream's frame before (inside the agent step at the physics rate, the agent step
  before at the agent rate; 0 difference at an episode's first frame, as the probe's clamping).
- `ReadoutObservation`: a fixed map of that observation (swingup-probe-state: the state a fitted probe
  predicts from it).
- `RawClip`: for an encoder trained jointly with the policy (pixels-cnn), the raw clip ("pixels", uint8
  [E, n, 3, H, W]) instead of an embedding.

`observed_env` builds the environment and its transforms for one encoder; the stream and clip rules are the
ones of the encoder's training data, so a policy sees exactly the embeddings the encoder gives the same
episode offline.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import Compose, ExcludeTransform, Transform, TransformedEnv

from mftcn_bench.core.errors import SpecError
from mftcn_bench.data.clips import ClipRing
from mftcn_bench.rl.observers import Observer
from mftcn_bench.rl.suite_env import SuiteBatchEnv, SuiteConfig


class Readout(Protocol):
    """A fixed map from the environment's observation rows [E, F] to what the policy sees, [E, out_features]
    (not trained by PPO)."""

    out_features: int

    def __call__(self, observation: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class PixelClip:
    """Emit the raw clip of `frames` frames at `stride` (for encoders trained with the policy)."""

    frames: int
    stride: int


def _stream(tensordict: TensorDictBase, pixels: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """The step's states [E, k, S] and frames [E, k, H, W, 3] (None without pixels) as numpy arrays."""
    frames = tensordict.get("frames").numpy() if pixels else None
    return tensordict.get("state").numpy(), frames


class EncoderEmbedding(Transform):
    """The observer's embedding of each agent step's last frame as "observation" (float32 [E, D], or
    [E, 2D] with `difference`)."""

    def __init__(self, observer: Observer, embedding_dim: int, pixels: bool, difference: bool) -> None:
        super().__init__(in_keys=["state", *(["frames"] if pixels else [])], out_keys=["observation"])
        self.observer, self.embedding_dim = observer, embedding_dim
        self.pixels, self.difference = pixels, difference
        self._last: np.ndarray | None = None  # e_{t-1} when it is the previous agent step's

    def _observation(self, embedding: np.ndarray, previous: np.ndarray) -> torch.Tensor:
        self._last = embedding
        if self.difference:
            embedding = np.concatenate([embedding, embedding - previous], axis=1)
        return torch.from_numpy(np.ascontiguousarray(embedding, dtype=np.float32))

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        state, frames = _stream(next_tensordict, self.pixels)
        k, num_envs = state.shape[1], state.shape[0]
        going = np.zeros(num_envs, dtype=bool)
        previous = self._last
        for j in range(k - 1):  # earlier frames of the step: the clip history (and e_{t-1} when it is inside)
            frame = None if frames is None else frames[:, j]
            if self.difference and j == k - 2:
                previous = self.observer.push(frame, going, state[:, j])
            else:
                self.observer.observe(frame, going, state[:, j])
        embedding = self.observer.push(None if frames is None else frames[:, -1], going, state[:, -1])
        next_tensordict.set("observation", self._observation(embedding, previous))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        state, frames = _stream(tensordict_reset, self.pixels)
        starting = np.ones(state.shape[0], dtype=bool)
        embedding = self.observer.push(None if frames is None else frames[:, -1], starting, state[:, -1])
        tensordict_reset.set("observation", self._observation(embedding, embedding))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        width = self.embedding_dim * (2 if self.difference else 1)
        observation_spec["observation"] = Unbounded(shape=(*observation_spec.shape, width), dtype=torch.float32)
        return observation_spec


class ReadoutObservation(Transform):
    """"observation" mapped by a fixed `Readout` (float32 [E, readout.out_features])."""

    def __init__(self, readout: Readout) -> None:
        super().__init__(in_keys=["observation"], out_keys=["observation"])
        self.readout = readout

    def _apply_transform(self, observation: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(self.readout(observation.numpy()), dtype=np.float32))

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec["observation"] = Unbounded(shape=(*observation_spec.shape, self.readout.out_features),
                                                    dtype=torch.float32)
        return observation_spec


class RawClip(Transform):
    """The raw clip ending at each agent step's last frame, channels first, as "pixels" (uint8 [E, n, 3, H, W])."""

    def __init__(self, clip: PixelClip, num_envs: int) -> None:
        super().__init__(in_keys=["frames"], out_keys=["pixels"])
        self.clip = clip
        self._window = ClipRing(clip.frames, clip.stride, num_envs)

    @property
    def lookback(self) -> int:
        """Frames the clip spans (the clip rule's, `data.clips`)."""
        return self._window.lookback

    def _push(self, frames: np.ndarray, start: bool) -> None:
        self._window.push(np.ascontiguousarray(frames.transpose(0, 3, 1, 2)), np.full(len(frames), start))

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        for frame in np.moveaxis(next_tensordict.get("frames").numpy(), 1, 0):
            self._push(frame, False)
        next_tensordict.set("pixels", torch.from_numpy(self._window.clip()))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._push(tensordict_reset.get("frames").numpy()[:, -1], True)
        tensordict_reset.set("pixels", torch.from_numpy(self._window.clip()))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        _, _, height, width, _ = observation_spec["frames"].shape
        observation_spec["pixels"] = Bounded(0, 255, shape=(*observation_spec.shape, self.clip.frames, 3, height,
                                                            width), dtype=torch.uint8)
        return observation_spec


def _stream_keys(env: SuiteBatchEnv) -> tuple[str, ...]:
    """What the environment emits and the policy never sees (a batch of PPO data would hold every frame)."""
    return ("state", "frames") if env.renders else ("state",)


def stream_frames(config: SuiteConfig, lookback: int) -> int:
    """The stream's frames an agent step must emit: those a clip of `lookback` frames reaches, and the one
    before the last when the difference's e_{t-1} lies inside the step."""
    inside = 2 if config.embedding_difference and config.frames_per_step > 1 else 1
    return min(max(lookback, inside), config.frames_per_step)


def observed_env(config: SuiteConfig, num_envs: int, seed: int, observer: Observer | None, embedding_dim: int,
                 observer_uses_pixels: bool, lookback: int = 1, pixel_clip: PixelClip | None = None,
                 readout: Readout | None = None) -> TransformedEnv:
    """`num_envs` environments of `config` whose observation is the observer's embedding (mapped by
    `readout`), or, with `pixel_clip` instead of an observer, the raw clip ("pixels")."""
    if (observer is None) == (pixel_clip is None):
        raise ValueError("give exactly one of observer and pixel_clip")
    if pixel_clip is not None:
        if config.embedding_difference:
            raise SpecError("[env] embedding_difference needs an encoder's embedding; an encoder trained with "
                            "the policy (pixels-cnn) gives the policy raw clips")
        if readout is not None:
            raise SpecError("a readout maps an encoder's embedding; an encoder trained with the policy "
                            "(pixels-cnn) gives the policy raw clips")
        raw = RawClip(pixel_clip, num_envs)
        env = SuiteBatchEnv(config, num_envs, seed, stream_frames(config, raw.lookback), renders=True)
        return TransformedEnv(env, Compose(raw, ExcludeTransform(*_stream_keys(env))))
    renders = observer_uses_pixels
    env = SuiteBatchEnv(config, num_envs, seed, stream_frames(config, lookback if renders else 1), renders)
    transforms: list[Transform] = [EncoderEmbedding(observer, embedding_dim, renders, config.embedding_difference)]
    if readout is not None:
        transforms.append(ReadoutObservation(readout))
    transforms.append(ExcludeTransform(*_stream_keys(env)))
    return TransformedEnv(env, Compose(*transforms))
