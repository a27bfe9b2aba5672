"""Pieces shared by the built-in encoders (mfTCN, TCN, the baselines, PVE, Shuffle and Learn, inception).

- `parse_table`: a spec's `[model]` or `[train]` table -> a dataclass; an unknown or missing key is a
  one-line `SpecError` naming the table.
- `save_payload` / `load_payload`: an atomic checkpoint file (written to a temporary file and renamed),
  read back with `torch.load(weights_only=True)`; a bad file is a one-line `BenchError`.
- `save_network` / `load_network`: the checkpoint of a module's weights plus the image shape (keys
  "model" and "image_shape").
- `to_images`, `map_batches`, `embed_episode_by_frames`: uint8 frames to tensors, a module applied in
  batches, and the per-episode embedding of a network split into `frame_features` and `head` (one base
  pass per frame, then the head over the gathered clips).
- `SpecEncoder`: the parts of the `Encoder` contract that every built-in encoder shares (`info`,
  `needs_fit`, the no-op `fit` of untrained encoders, `save` / `load` of `net`); encoders override the rest.
  `MovableEncoder` adds `to_device` for encoders whose code follows `self.device` (PVE and every
  `FrameHeadEncoder`); `FrameHeadEncoder` adds `embed` / `embed_episode` for a `net` that embeds whole clips
  and splits into `frame_features` / `head` (mfTCN, TCN, pixels-cnn).
"""

from __future__ import annotations

import io
import pickle
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import torch
from torch import nn

from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.core.specs import parse_table as parse_spec_table
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import ClipBatch, EncoderInfo, FitBudget, ProgressFn
from mftcn_bench.encoders.streaming import FrameHeadNet

T = TypeVar("T")
CPU = torch.device("cpu")


def parse_table(cls: type[T], encoder: str, section: str, table: Mapping[str, Any]) -> T:
    """`core.specs.parse_table` for an encoder's `[model]` or `[train]` table."""
    return parse_spec_table(cls, f"encoder {encoder!r}", section, table)


def save_payload(path: Path, payload: Any) -> None:
    """`torch.save`, written atomically (`atomic_write_bytes`: flushed to disk, then renamed over `path`)."""
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def load_failure(exc: BaseException) -> str:
    """Why `torch.load(weights_only=True)` refused a file, in a few words (its own messages span lines)."""
    if isinstance(exc, pickle.UnpicklingError):
        return "it holds pickled Python objects, which are never loaded; only tensors and plain data are"
    if isinstance(exc, EOFError | RuntimeError):
        return f"{type(exc).__name__}: truncated or not a torch checkpoint"
    return type(exc).__name__


def unloadable(path: Path, exc: BaseException, redo: str) -> BenchError:
    """The one-line error for a checkpoint that cannot be read; `redo` is what deleting it leads to."""
    return BenchError(f"encoder checkpoint {path} cannot be loaded ({load_failure(exc)}); "
                      f"rerun with --force (or delete it) to {redo} again")


def load_payload(path: Path) -> Any:
    """Inverse of `save_payload` for a small checkpoint that is rebuilt rather than trained."""
    try:
        return torch.load(path, weights_only=True, map_location="cpu")
    except Exception as exc:  # noqa: BLE001 - truncated or foreign file
        raise unloadable(path, exc, "build it") from None


def save_network(path: Path, net: nn.Module, image_shape: tuple[int, int]) -> None:
    """Weights and image shape, written to a temporary file and renamed."""
    save_payload(path, {"model": net.state_dict(), "image_shape": list(image_shape)})


def load_network(path: Path, net: nn.Module, image_shape: tuple[int, int], device: torch.device = CPU) -> None:
    """Inverse of `save_network`, onto `device` (a checkpoint written on a GPU loads on a CPU-only machine);
    a bad file or another image shape is a one-line error."""
    try:
        state = torch.load(path, weights_only=True, map_location=device)
        net.load_state_dict(state["model"])
    except Exception as exc:  # noqa: BLE001 - truncated, foreign or mismatched file
        raise unloadable(path, exc, "train") from None
    if tuple(state["image_shape"]) != tuple(image_shape):
        trained = tuple(state["image_shape"])
        raise SpecError(f"encoder checkpoint {path} was trained on {trained[0]}x{trained[1]} (HxW) images, not "
                        f"{image_shape[0]}x{image_shape[1]}; it only embeds {trained[0]}x{trained[1]} frames: "
                        f"use a dataset of that size or rerun with --force to train it on these")
    net.eval()


def to_images(frames: np.ndarray) -> torch.Tensor:
    """uint8 numpy frames [..., H, W, 3] -> uint8 tensor [..., 3, H, W]."""
    tensor = torch.from_numpy(np.ascontiguousarray(frames))
    return tensor.movedim(-1, -3)


def map_batches(fn: Callable[[torch.Tensor], torch.Tensor], inputs: torch.Tensor,
                batch_size: int) -> torch.Tensor:
    """`fn` applied to consecutive slices of `batch_size` rows of `inputs`, concatenated."""
    return torch.cat([fn(inputs[i:i + batch_size]) for i in range(0, len(inputs), batch_size)])


def embed_episode_by_frames(net: FrameHeadNet, frames: np.ndarray, frames_per_clip: int, stride: int,
                            batch_size: int, device: torch.device = CPU) -> np.ndarray:
    """Embeddings of the clips ending at every frame of one view [T, H, W, 3]: one `frame_features` pass
    per frame, then `head` over the per-frame features gathered by `clip_indices`, in batches (on
    `device`, where `net` is)."""
    features = map_batches(lambda rows: net.frame_features(rows.to(device)), to_images(frames), batch_size)
    index = torch.from_numpy(clip_indices(np.arange(len(frames)), frames_per_clip, stride)).to(device)
    out = map_batches(lambda rows: net.head(features[rows]), index, batch_size)
    return to_numpy(out)


def to_numpy(out: torch.Tensor) -> np.ndarray:
    """Embeddings on any device -> float32 numpy on the CPU."""
    return out.detach().cpu().numpy().astype(np.float32, copy=False)


def check_image_shape(expected: tuple[int, int], dataset: MultiViewDataset) -> None:
    if dataset.image_shape != expected:
        raise SpecError(f"encoder built for {expected} images cannot train on {dataset.image_shape} frames")


class SpecEncoder:
    """Shared `Encoder` parts of an encoder built from a spec: `cls(spec, image_shape=(H, W), seed=seed)`.

    Subclasses set `net` (the torch module whose weights are checkpointed, or None), implement `embed`,
    and override `needs_fit` and `fit` when they train, `save` / `load` when they keep something else.
    """

    needs_fit: bool = False

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        self.spec, self.image_shape, self.seed = spec, tuple(image_shape), seed
        self.net: nn.Module | None = None
        self.device = CPU  # where `net` computes; encoders that can move set it in `to_device`

    def counted_module(self) -> nn.Module | None:
        """The module whose parameters `info` reports: `net` unless the embedding uses only part of it."""
        return self.net

    @property
    def info(self) -> EncoderInfo:
        module = self.counted_module()
        count = 0 if module is None else sum(p.numel() for p in module.parameters())
        return EncoderInfo(self.spec.name, self.spec.frames, self.spec.stride, self.image_shape,
                           self.spec.embedding_dim, count)

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        """Nothing to train (`needs_fit` is False)."""
        return {"steps": 0.0}

    def _network(self) -> nn.Module:
        if self.net is None:
            raise BenchError(f"encoder {self.spec.name!r} has no network to checkpoint")
        return self.net

    def save(self, path: Path) -> None:
        save_network(path, self._network(), self.image_shape)

    def load(self, path: Path) -> None:
        load_network(path, self._network(), self.image_shape, self.device)


class MovableEncoder(SpecEncoder):
    """A `SpecEncoder` whose every tensor follows `self.device`: `to_device` (`core.device.DevicePlaced`)
    moves `net` there, and training, embedding and streaming send their inputs there."""

    def to_device(self, device: torch.device) -> None:
        self.device = torch.device(device)
        self._network().to(self.device)


class FrameHeadEncoder(MovableEncoder):
    """A `SpecEncoder` whose `net` maps uint8 clips [B, n, 3, H, W] to [B, D] and has the `frame_features`
    / `head` split, so an episode is embedded with one `frame_features` pass per frame."""

    @torch.no_grad()
    def embed(self, clips: ClipBatch) -> np.ndarray:
        return to_numpy(self._network()(to_images(clips.frames).to(self.device)))

    @torch.no_grad()
    def embed_episode(self, frames: np.ndarray, state: np.ndarray | None = None,
                      batch_size: int = 256) -> np.ndarray:
        """Embeddings of the clips ending at every frame of one view [T, H, W, 3]: one per-frame pass
        per frame, then the head over gathered features (`embed_episode_by_frames`)."""
        net = cast(FrameHeadNet, self._network())
        return embed_episode_by_frames(net, frames, self.spec.frames, self.spec.stride, batch_size, self.device)
