"""The encoder contract: what a third-party encoder implements to be benchmarked.

An encoder class is constructed as `cls(spec, image_shape=(H, W), seed=seed)` and then satisfies
`Encoder`. The harness calls `fit` once per (spec, dataset, seed) and reuses the saved result across
tasks, then embeds clips. Frames are uint8 RGB; a clip is the frames t-(n-1)s, ..., t of one view
(oldest first, see `mftcn_bench.data.clips`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.progress import Progress
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.privileged import Withheld, visible

if TYPE_CHECKING:
    import torch
    from torch import nn

    from mftcn_bench.encoders.feature_cache import FeatureCache


@dataclass(frozen=True)
class EncoderInfo:
    """Metadata recorded with every result of an encoder."""

    name: str
    frames: int
    stride: int
    image_shape: tuple[int, int]
    embedding_dim: int
    parameter_count: int

    @property
    def lookback(self) -> int:
        return (self.frames - 1) * self.stride + 1


@dataclass(frozen=True)
class ClipBatch:
    """Clips to embed: frames [B, n, H, W, 3] uint8 and the matching true state [B, n, S] when known and the
    encoder declares it (`encoders.privileged`); a `Withheld` marker when the harness withholds it."""

    frames: np.ndarray
    state: np.ndarray | Withheld | None = None


@dataclass(frozen=True)
class FitBudget:
    """How much training `fit` may do: optimizer steps, and optionally a wall-clock limit."""

    steps: int
    max_seconds: float | None = None


def fit_budget(encoder: str, train: Mapping[str, Any]) -> FitBudget:
    """The budget of a fit from the encoder's `[train]` table. `steps` is required: the tasks' presets set
    `encoder.train.steps` only where the spec has it, so a spec without it would fit for no steps at all."""
    steps = train.get("steps")
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise SpecError(f"encoder {encoder!r} needs a fit and its spec's [train] table has no integer steps >= 1 "
                        f"(got {steps!r}); add `steps = N` under [train] (the tasks' presets then set it per task)")
    seconds = train.get("max_seconds")
    return FitBudget(steps=steps, max_seconds=float(seconds) if seconds else None)


# A fit's learning curve in its workdir: {"step": [...], "<measure>": [...], ...}.
FIT_CURVE = "fit_curve.json"

# progress(step, total_steps, {"loss": ...}) is called as training goes (the harness's one progress type).
ProgressFn = Progress


@runtime_checkable
class Encoder(Protocol):
    """A frozen-after-fit map from clips to embeddings."""

    @property
    def info(self) -> EncoderInfo: ...

    @property
    def needs_fit(self) -> bool:
        """False for encoders without a training signal (random features, true state)."""
        ...

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        """Train on the dataset's train split; may checkpoint into `workdir` and resume from it.
        Returns summary statistics (for example the final loss). A learning curve goes to
        `workdir / FIT_CURVE` (JSON columns of equal length), which the runner records as the run's `fit`
        curve."""
        ...

    def embed(self, clips: ClipBatch) -> np.ndarray:
        """float32 [B, embedding_dim]."""
        ...

    def save(self, path: Path) -> None: ...

    def load(self, path: Path) -> None: ...


@runtime_checkable
class FrozenFrameBase(Protocol):
    """A frozen per-frame network whose features the harness caches once per data set and shares between
    encoders (the built-in `encoders.bases.FrozenBase`, or a plugin's own backbone): it must give the same
    features for a frame whoever asks, so it never trains."""

    def identity(self) -> dict[str, Any]:
        """Everything its features depend on besides its code (settings, the weights' checksum): with the
        class's code it keys the cache, so another base never reads these features."""
        ...

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 frames [B, 3, H, W] on the base's device -> float features [B, C, h, w]."""
        ...


@runtime_checkable
class FeatureCacheUser(Protocol):
    """Optional capability: an encoder on a frozen per-frame base whose features the harness caches.

    Before `fit` and evaluation the runner builds (or finds) the cache of `frozen_base()` on the run's
    dataset and hands it over with `use_feature_cache`; the encoder then reads base features from it
    instead of running the base on frames it holds."""

    def frozen_base(self) -> FrozenFrameBase | None:
        """The frozen base, or None when this encoder's base trains (then nothing is cached)."""
        ...

    def use_feature_cache(self, cache: FeatureCache) -> None: ...


@runtime_checkable
class EpisodeEmbedder(Protocol):
    """Optional capability: embeds every clip of one episode at once (sharing per-frame work between
    overlapping clips). Must equal `embed` of the same clips (`mftcn-bench check encoder` tests it)."""

    def embed_episode(self, frames: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """frames uint8 [T, H, W, 3] of one view (state [T, S] or None) -> float32 [T, D]: the embedding
        of the clip ending at each frame, clips built by `mftcn_bench.data.clips`."""
        ...


@runtime_checkable
class Stream(Protocol):
    """An incremental embedder of `num_envs` environments stepped together (from `streaming`)."""

    def push(self, frames: np.ndarray | None, episode_start: np.ndarray,
             state: np.ndarray | Withheld | None) -> np.ndarray:
        """frames uint8 [E, H, W, 3] (None for an encoder that does not use pixels), episode_start bool [E],
        state float [E, S] (`Withheld` unless the encoder declares it) -> float32 [E, D], the embedding of the
        clip ending at each new frame."""
        ...


@runtime_checkable
class HistoryStream(Stream, Protocol):
    """A stream that can take a frame into its history without embedding it (the inner steps of an
    action repeat); a `Stream` without it is pushed instead."""

    def observe(self, frames: np.ndarray | None, episode_start: np.ndarray,
                state: np.ndarray | Withheld | None) -> None: ...


@runtime_checkable
class StreamingEncoder(Protocol):
    """Optional capability: an incremental embedder for rollouts, equal to `embed` of the same clips.
    Without it a rollout keeps the raw frames of the lookback window and calls `embed` every step."""

    def streaming(self, num_envs: int) -> Stream: ...


@runtime_checkable
class MultiViewTrainer(Protocol):
    """Optional declaration: an encoder whose training needs `training_views` cameras' views of each
    moment (time-contrastive: 2); a task whose dataset has fewer is refused before any data is collected."""

    training_views: int


@runtime_checkable
class PixelUse(Protocol):
    """Optional declaration: `uses_pixels = False` for an encoder that reads only `ClipBatch.state`
    (rollouts then render nothing for it). Encoders without it read pixels."""

    uses_pixels: bool


@runtime_checkable
class PolicyTrainedEncoder(Protocol):
    """Optional capability: an encoder with no training signal of its own, whose `net` (uint8 clips
    [B, n, 3, H, W] -> [B, D]) the control tasks train jointly with the policy (pixels-cnn)."""

    trains_with_policy: bool

    @property
    def net(self) -> nn.Module: ...


def uses_pixels(encoder: Encoder) -> bool:
    """Whether the encoder reads rendered frames (true state and random state do not)."""
    return encoder.uses_pixels if isinstance(encoder, PixelUse) else True


def trains_with_policy(encoder: Encoder) -> bool:
    return isinstance(encoder, PolicyTrainedEncoder) and encoder.trains_with_policy


def embed_episode(encoder: Encoder, frames: np.ndarray, state: np.ndarray | None = None,
                  batch_size: int = 256) -> np.ndarray:
    """Embeddings [T, D] of the clips ending at every frame of one view of an episode.

    Uses the encoder's own `embed_episode(frames, state)` when it is an `EpisodeEmbedder`; otherwise
    builds the clips and calls `embed` in batches (`embed_clips_of_episode`). The state reaches the encoder
    only if it declares it (`encoders.privileged`).
    """
    state = visible(encoder, "state", state)
    if isinstance(encoder, EpisodeEmbedder):
        out = encoder.embed_episode(frames, state)
    else:
        out = embed_clips_of_episode(encoder, frames, state, batch_size)
    return check_embeddings(encoder, out, len(frames))


def embed_clips_of_episode(encoder: Encoder, frames: np.ndarray, state: np.ndarray | None = None,
                           batch_size: int = 256) -> np.ndarray:
    """`embed_episode` through `embed` alone: every clip of the episode built and embedded in batches."""
    state = visible(encoder, "state", state)
    info = encoder.info
    index = clip_indices(np.arange(len(frames)), info.frames, info.stride)
    parts = []
    for start in range(0, len(frames), batch_size):
        rows = index[start:start + batch_size]
        batch = ClipBatch(frames[rows], state if state is None or isinstance(state, Withheld) else state[rows])
        parts.append(check_embeddings(encoder, encoder.embed(batch), len(rows)))
    return np.concatenate(parts)


def check_embeddings(encoder: Encoder, out: np.ndarray, rows: int) -> np.ndarray:
    """Validate a plugin's output at the boundary: shape, dtype, finiteness."""
    name, dim = encoder.info.name, encoder.info.embedding_dim
    if not isinstance(out, np.ndarray) or out.shape != (rows, dim):
        shape = getattr(out, "shape", type(out).__name__)
        raise BenchError(f"encoder {name!r} returned embeddings of shape {shape}; expected ({rows}, {dim})")
    if out.dtype != np.float32:
        raise BenchError(f"encoder {name!r} returned embeddings of dtype {out.dtype}; expected float32")
    if not np.isfinite(out).all():
        raise BenchError(f"encoder {name!r} returned non-finite embeddings (NaN or inf)")
    return out
