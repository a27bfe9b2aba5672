"""Multi-view datasets on disk: a manifest and one compressed chunk per episode.

Layout of `<home>/datasets/<name>-<id>/`:
    manifest.json      config, seed, versions, per-chunk checksums; written last, atomically
    progress.json      chunks finished so far while collecting (lets a killed collection resume)
    ep00000.npz ...    per episode: frames [views, T, H, W, 3] uint8, state [T, S], action [T, A], and
                       optionally labels [T, L] (int, per-frame attributes; -1 where unknown)

The dataset id is a hash of its config and the collector's format version, so the same spec and seed
reuse the dataset. Episodes are loaded one at a time (with a small cache), never the whole dataset.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mftcn_bench.core import identity
from mftcn_bench.core.errors import DataError
from mftcn_bench.core.fileio import atomic_write_bytes, exclusive_lock, resume_folder
from mftcn_bench.core.progress import progress_bar
from mftcn_bench.core.provenance import content_hash, versions
from mftcn_bench.data.chunks import read_chunk, write_chunk
from mftcn_bench.sim.rendering import gl_renderer

FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")  # "val" only holds episodes when the config asks for val_episodes

# An episode collector: (dataset config, episode index) -> arrays of that episode.
Collector = Callable[[Mapping[str, Any], int], dict[str, np.ndarray]]


@dataclass(frozen=True)
class Episode:
    """One episode's synchronized views and per-frame records."""

    index: int
    frames: np.ndarray  # [views, T, H, W, 3] uint8
    state: np.ndarray  # [T, S] true state as the simulator gives it
    action: np.ndarray  # [T, A] action taken after frame t was observed
    labels: np.ndarray | None = None  # [T, L] per-frame attributes, for datasets that have them

    @property
    def length(self) -> int:
        return int(self.frames.shape[1])


class MultiViewDataset:
    """A collected dataset, read episode by episode."""

    def __init__(self, root: Path, cache_episodes: int = 2) -> None:
        self.root = Path(root)
        manifest_path = self.root / "manifest.json"
        if not manifest_path.exists():
            raise DataError(f"{self.root} is not a collected dataset (no manifest.json)")
        try:
            self.manifest: dict[str, Any] = json.loads(manifest_path.read_text())
            self._chunks = {int(c["episode"]): c for c in self.manifest["chunks"]}
        except (ValueError, KeyError, TypeError) as exc:
            raise DataError(f"dataset manifest {manifest_path} is not a valid manifest ({type(exc).__name__}: "
                            f"{exc}); delete the folder {self.root} to collect the dataset again") from None
        if not self._chunks:
            raise DataError(f"dataset {self.root} is empty: its manifest lists no episodes; delete the folder "
                            f"to collect it again")
        self._cache: OrderedDict[int, Episode] = OrderedDict()
        self._cache_size = cache_episodes

    @property
    def dataset_id(self) -> str:
        return self.manifest["id"]

    @property
    def config(self) -> Mapping[str, Any]:
        return self.manifest["config"]

    @property
    def cameras(self) -> list[str]:
        return list(self.config["cameras"])

    @property
    def image_shape(self) -> tuple[int, int]:
        return int(self.config["height"]), int(self.config["width"])

    @property
    def fingerprint(self) -> str:
        """A hash of the id and every chunk's checksum: what a result's identity depends on."""
        return content_hash([self.dataset_id, [c["sha256"] for c in self.manifest["chunks"]]])

    def episodes(self, split: str) -> list[int]:
        if split not in SPLITS:
            raise DataError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
        return sorted(i for i, c in self._chunks.items() if c["split"] == split)

    def episode_length(self, index: int) -> int:
        return int(self._chunks[index]["length"])

    def load(self, index: int) -> Episode:
        """Episode `index`, checked against its checksum when first read."""
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        chunk = self._chunks.get(index)
        if chunk is None:
            raise DataError(f"dataset {self.root} has no episode {index}")
        arrays = read_chunk(self.root / chunk["file"], chunk["sha256"])
        episode = Episode(index, arrays["frames"], arrays["state"], arrays["action"], arrays.get("labels"))
        self._cache[index] = episode
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return episode

    def iter_episodes(self, split: str) -> Iterator[Episode]:
        for index in self.episodes(split):
            yield self.load(index)


def dataset_id(config: Mapping[str, Any], collector: Collector) -> str:
    """The dataset's identity: its config, the file format, the collector's code and this machine's GL
    renderer (`identity`, `sim.rendering.gl_renderer`)."""
    return identity.dataset_id(config, collector, FORMAT_VERSION, gl_renderer())


def _episode_plan(config: Mapping[str, Any]) -> list[tuple[int, str]]:
    train, test = int(config["train_episodes"]), int(config["test_episodes"])
    if train < 1 or test < 1:
        raise DataError(f"a dataset needs at least 1 train and 1 test episode, got {train} and {test}; "
                        f"set train_episodes and test_episodes >= 1")
    val = int(config.get("val_episodes", 0))
    if val < 0:
        raise DataError(f"val_episodes must be >= 0, got {val}")
    return ([(i, "train") for i in range(train)] + [(train + i, "val") for i in range(val)]
            + [(train + val + i, "test") for i in range(test)])


def check_dataset_config(config: Mapping[str, Any]) -> None:
    """Refuse, before anything is collected, sizes no dataset can have (episode counts, frames, pixels)."""
    if "train_episodes" in config and "test_episodes" in config:
        _episode_plan(config)
    for key in ("episode_length", "height", "width"):
        value = config.get(key, 1)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise DataError(f"dataset {config.get('name')!r}: {key} must be an integer >= 1, got {value!r}")


def dataset_root(datasets_dir: Path, config: Mapping[str, Any], collector: Collector) -> Path:
    """Where the dataset for `config` lives (collected or not) under `datasets_dir`."""
    return datasets_dir / f"{config['name']}-{dataset_id(config, collector)}"


def find_dataset(datasets_dir: Path, config: Mapping[str, Any], collector: Collector) -> MultiViewDataset | None:
    """The dataset for `config` if it has been collected to the end, else None (nothing is collected)."""
    root = dataset_root(datasets_dir, config, collector)
    return MultiViewDataset(root) if (root / "manifest.json").exists() else None


def ensure_dataset(
    datasets_dir: Path, config: Mapping[str, Any], collector: Collector, *, show_progress: bool = True
) -> MultiViewDataset:
    """The dataset for `config`, collected (or finished, after an interruption) if needed."""
    check_dataset_config(config)
    found = find_dataset(datasets_dir, config, collector)
    if found is not None:
        return found
    ident, root = dataset_id(config, collector), dataset_root(datasets_dir, config, collector)
    with exclusive_lock(datasets_dir / f".{root.name}.lock"):
        if (root / "manifest.json").exists():  # another process finished it while we waited
            return MultiViewDataset(root)
        done = resume_folder(root)
        progress_path = root / "progress.json"
        plan = _episode_plan(config)
        total, chunks = len(plan) * int(config["episode_length"]), []
        with progress_bar(f"collect {config['name']}", "frame", show_progress) as report:
            for index, split in plan:
                name = f"ep{index:05d}.npz"
                entry = done.get(name)
                if entry is None or not (root / name).exists():
                    arrays = collector(config, index)
                    sha = write_chunk(root / name, arrays)
                    entry = {"file": name, "episode": index, "split": split,
                             "length": int(arrays["frames"].shape[1]), "sha256": sha}
                    done[name] = entry
                    atomic_write_bytes(progress_path, json.dumps(list(done.values()), indent=1).encode())
                chunks.append(entry)
                report(len(chunks) * int(config["episode_length"]), total, {})
        manifest = {"id": ident, "format": FORMAT_VERSION, "config": dict(config), "seed": config["seed"],
                    "versions": versions(), "renderer": gl_renderer(), "chunks": chunks}
        atomic_write_bytes(root / "manifest.json", json.dumps(manifest, indent=1, sort_keys=True).encode())
        progress_path.unlink(missing_ok=True)
        return MultiViewDataset(root)

