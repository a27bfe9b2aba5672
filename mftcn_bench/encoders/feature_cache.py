"""Per-frame features of a frozen base for every frame of every view of a dataset, computed once.

A frozen base gives the same features for a frame whoever asks, so encoder fits, probes, pouring
evaluations and sweep jobs that share a base and a dataset share one cache. Layout of
`<home>/features/<dataset name>-<id>/`:

    manifest.json     base identity, dataset fingerprint, feature shape, per-episode checksums; written
                      last, atomically
    progress.json     episodes finished so far (a killed build resumes there)
    ep00000.npy ...   float32 [views, T, C, h, w], read memory-mapped (never the whole cache in memory)

The id (`identity.feature_cache_id`) hashes the dataset's fingerprint, the base's settings, weights
checksum and code, so a changed base or dataset never reads another's features. Each episode also records
the sha256 of each view's frames, so `lookup(frames)` finds cached features by content (an embedding call
that passes frames gets the cache without knowing episode numbers) and can never return another clip's
features.
"""

from __future__ import annotations

import hashlib
import io
import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from mftcn_bench.core import identity
from mftcn_bench.core.device import CPU, Placement
from mftcn_bench.core.errors import DataError
from mftcn_bench.core.fileio import atomic_write_bytes, exclusive_lock, resume_folder
from mftcn_bench.core.progress import progress_bar
from mftcn_bench.core.provenance import file_sha256
from mftcn_bench.data.dataset import MultiViewDataset

if TYPE_CHECKING:
    from mftcn_bench.encoders.base import FrozenFrameBase

FORMAT_VERSION = 1


def frames_digest(frames: np.ndarray) -> str:
    """sha256 of one view's frames [T, H, W, 3] (shape and bytes)."""
    digest = hashlib.sha256(repr((frames.shape, str(frames.dtype))).encode())
    digest.update(np.ascontiguousarray(frames).data)
    return digest.hexdigest()


@torch.no_grad()
def base_features(base: FrozenFrameBase, frames: np.ndarray, batch_size: int,
                  device: torch.device | None = None) -> np.ndarray:
    """float32 [T, C, h, w] base features of uint8 frames [T, H, W, 3], in batches on `device` (where
    `base` is; the CPU by default)."""
    images = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2)
    target = device or torch.device("cpu")
    parts = [base(images[i:i + batch_size].to(target)).cpu() for i in range(0, len(images), batch_size)]
    return torch.cat(parts).numpy().astype(np.float32, copy=False)


class FeatureCache:
    """A built cache: features of episode i, or of frames found by content."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        path = self.root / "manifest.json"
        try:
            self.manifest: dict[str, Any] = json.loads(path.read_text())
            self._entries = {int(e["episode"]): e for e in self.manifest["episodes"]}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DataError(f"feature cache manifest {path} cannot be read ({type(exc).__name__}); delete the "
                            f"folder {self.root} to build the cache again") from None
        self._by_content = {digest: (int(e["episode"]), view) for e in self.manifest["episodes"]
                            for view, digest in enumerate(e["frames_sha256"])}
        self._verified: set[int] = set()

    @property
    def cache_id(self) -> str:
        return self.manifest["id"]

    @property
    def size_bytes(self) -> int:
        return int(sum(e["bytes"] for e in self.manifest["episodes"]))

    def summary(self) -> dict[str, Any]:
        """What a run records about the cache it used."""
        return {"id": self.cache_id, "path": str(self.root), "bytes": self.size_bytes,
                "build_s": self.manifest["build_s"], "frames": self.manifest["frames"],
                "feature_shape": self.manifest["feature_shape"]}

    def load(self, episode: int) -> np.ndarray:
        """float32 [views, T, C, h, w] of `episode`, memory-mapped; checked against its checksum once."""
        entry = self._entries.get(episode)
        if entry is None:
            raise DataError(f"feature cache {self.root} has no episode {episode}")
        path = self.root / entry["file"]
        if episode not in self._verified:
            if not path.exists() or file_sha256(path) != entry["sha256"]:
                raise DataError(f"feature cache file {path} is missing or does not match its checksum; delete "
                                f"the folder {self.root} to build the cache again")
            self._verified.add(episode)
        return np.load(path, mmap_mode="r", allow_pickle=False)

    def lookup(self, frames: np.ndarray) -> np.ndarray | None:
        """The cached features [T, C, h, w] of one view's frames [T, H, W, 3], or None if not cached."""
        found = self._by_content.get(frames_digest(frames))
        if found is None:
            return None
        episode, view = found
        return self.load(episode)[view]


def cache_id(dataset: MultiViewDataset, base: FrozenFrameBase, base_identity: Mapping[str, Any],
             placement: Placement = CPU) -> str:
    """The cache's identity: the dataset, the base's settings and weights, its code, the cache format and
    the device whose base passes computed it."""
    return identity.feature_cache_id(dataset.fingerprint, base_identity, base, FORMAT_VERSION,
                                     placement.identity())


def ensure_feature_cache(features_dir: Path, dataset: MultiViewDataset, base: FrozenFrameBase,
                         base_identity: Mapping[str, Any], *, batch_size: int = 64,
                         show_progress: bool = True, placement: Placement = CPU) -> FeatureCache:
    """The cache of `base`'s features on every episode of `dataset`, built (or finished) if needed; the base
    runs on `placement`'s device (where it must already be)."""
    ident = cache_id(dataset, base, base_identity, placement)
    root = features_dir / f"{dataset.config['name']}-{ident}"
    if (root / "manifest.json").exists():
        return FeatureCache(root)
    with exclusive_lock(features_dir / f".{root.name}.lock"):
        if (root / "manifest.json").exists():  # another process built it while we waited
            return FeatureCache(root)
        done = resume_folder(root)
        progress_path = root / "progress.json"
        episodes = sorted(i for split in ("train", "val", "test") for i in dataset.episodes(split))
        total = sum(dataset.episode_length(i) for i in episodes) * len(dataset.cameras)
        began, shape, computed_s, embedded = time.monotonic(), None, 0.0, 0
        with progress_bar(f"features {dataset.config['name']}", "frame", show_progress) as report:
            for index in episodes:
                name = f"ep{index:05d}.npy"
                entry = done.get(name)
                if entry is None or not (root / name).exists():
                    episode = dataset.load(index)
                    start = time.monotonic()
                    stacked = np.stack([base_features(base, view, batch_size, placement.torch_device)
                                        for view in episode.frames])
                    computed_s += time.monotonic() - start
                    buffer = _npy_bytes(stacked)
                    atomic_write_bytes(root / name, buffer)
                    entry = {"file": name, "episode": index, "length": int(stacked.shape[1]),
                             "sha256": hashlib.sha256(buffer).hexdigest(), "bytes": len(buffer),
                             "frames_sha256": [frames_digest(view) for view in episode.frames],
                             "feature_shape": list(stacked.shape[2:])}
                    done[name] = entry
                    atomic_write_bytes(progress_path, json.dumps(list(done.values()), indent=1).encode())
                shape = entry["feature_shape"]
                embedded += entry["length"] * len(dataset.cameras)
                report(embedded, total, {})
        ordered = [done[f"ep{i:05d}.npy"] for i in episodes]
        manifest = {"id": ident, "format": FORMAT_VERSION, "dataset": dataset.fingerprint,
                    "dataset_path": str(dataset.root), "base": dict(base_identity), "feature_shape": shape,
                    "frames": total, "device": placement.record(), "build_s": round(time.monotonic() - began, 3),
                    "base_forward_s": round(computed_s, 3), "episodes": ordered}
        atomic_write_bytes(root / "manifest.json", json.dumps(manifest, indent=1, sort_keys=True).encode())
        progress_path.unlink(missing_ok=True)
        return FeatureCache(root)


def _npy_bytes(array: np.ndarray) -> bytes:
    out = io.BytesIO()
    np.lib.format.write_array(out, np.ascontiguousarray(array), allow_pickle=False)
    return out.getvalue()
