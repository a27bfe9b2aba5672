"""The encoder contract: what a third-party encoder implements to be benchmarked.

An encoder class is constructed as `cls(spec, image_shape=(H, W), seed=seed)` and then satisfies
`Encoder`. The harness calls `fit` once per (spec, dataset, seed) and reuses the saved result across
tasks, then embeds clips. Frames are uint8 RGB; a clip is the frames t-(n-1)s, ..., t of one view
(oldest first, see `mftcn_bench.data.clips`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from mftcn_bench.data.clips import clip_indices
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.errors import BenchError

if TYPE_CHECKING:
    from mftcn_bench.encoders.bases import FrozenBase
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
    """Clips to embed: frames [B, n, H, W, 3] uint8 and the matching true state [B, n, S] if known."""

    frames: np.ndarray
    state: np.ndarray | None = None


@dataclass(frozen=True)
class FitBudget:
    """How much training `fit` may do: optimizer steps, and optionally a wall-clock limit."""

    steps: int
    max_seconds: float | None = None


# progress(step, total_steps, {"loss": ...}) is called as training goes.
ProgressFn = Callable[[int, int, dict[str, float]], None]


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
        Returns summary statistics (for example the final loss)."""
        ...

    def embed(self, clips: ClipBatch) -> np.ndarray:
        """float32 [B, embedding_dim]."""
        ...

    def save(self, path: Path) -> None: ...

    def load(self, path: Path) -> None: ...


@runtime_checkable
class FeatureCacheUser(Protocol):
    """Optional capability: an encoder on a frozen per-frame base whose features the harness caches.

    Before `fit` and evaluation the runner builds (or finds) the cache of `frozen_base()` on the run's
    dataset and hands it over with `use_feature_cache`; the encoder then reads base features from it
    instead of running the base on frames it holds."""

    def frozen_base(self) -> FrozenBase | None:
        """The frozen base, or None when this encoder's base trains (then nothing is cached)."""
        ...

    def use_feature_cache(self, cache: FeatureCache) -> None: ...


def embed_episode(encoder: Encoder, frames: np.ndarray, state: np.ndarray | None = None,
                  batch_size: int = 256) -> np.ndarray:
    """Embeddings [T, D] of the clips ending at every frame of one view of an episode.

    Uses the encoder's own `embed_episode(frames, state)` when it has one (it can share per-frame work
    between overlapping clips); otherwise builds the clips and calls `embed` in batches.
    """
    own = getattr(encoder, "embed_episode", None)
    if own is not None:
        out = own(frames, state)
    else:
        info = encoder.info
        index = clip_indices(np.arange(len(frames)), info.frames, info.stride)
        parts = []
        for start in range(0, len(frames), batch_size):
            rows = index[start:start + batch_size]
            batch = ClipBatch(frames[rows], None if state is None else state[rows])
            parts.append(check_embeddings(encoder, encoder.embed(batch), len(rows)))
        out = np.concatenate(parts)
    return check_embeddings(encoder, out, len(frames))


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
