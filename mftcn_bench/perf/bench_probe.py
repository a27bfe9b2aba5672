"""Peak memory (RSS) of the cartpole probe's whole pipeline, measured in a child process.

The paper-scale probe embeds 180,000 frames (160 train + 20 test episodes of 1000 frames, 2 views) and
fits an MLP on all the features; at 160x160 the raw frames are ~27 GB, so the pipeline must stream
episodes. Its two phases are measured separately, each in a fresh process, by the peak RSS (`VmHWM` of
/proc/self/status, reset between phases through /proc/self/clear_refs):

- Embedding (`measure_embedding`): `CartpoleProbe.evaluate` exactly as a run calls it (mftcn4 reading
  its frozen base's feature cache, which is built first in the same process), on a synthetic
  dataset written with the real chunk writer (frames constant within each frame, so chunks are small and
  fast to write; the network's cost and the arrays' sizes do not depend on pixel values) of a few
  full-size episodes. Embedding all 180,000 frames at 160x160 takes over an hour on one core, and
  episodes are embedded one at a time, so this phase's peak does not grow with the number of episodes
  except by the features kept so far (and some allocator fragmentation); the paper-scale figure adds
  the measured growth per frame (`paper_scale_peak`).
- Fit (`measure_fit`): `CartpoleProbe.evaluate` at the full 160,000 + 20,000 frames, its `features` fed
  per-episode arrays of the real shapes and dtypes (`probe_features` of float32 embeddings, `state_targets`),
  concatenated as the task does: this phase is measured at paper scale, not extrapolated.

Child entry points print one JSON line: `python -m mftcn_bench.perf.bench_probe embed DATASET_ROOT [ENCODER]`,
`python -m mftcn_bench.perf.bench_probe fit TRAIN_FRAMES TEST_FRAMES EPISODE_LENGTH [EPOCHS]`.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

PROBE_CAMERAS = ["fixed", "lookatcart"]
PAPER_TRAIN_FRAMES, PAPER_TEST_FRAMES = 160_000, 20_000
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


@dataclass(frozen=True)
class ProbeMemory:
    """Peak RSS (bytes) of one probe run's phases, and what it probed."""

    frames: int  # train + test frames (one view)
    embed_peak: int  # from the start to the end of embedding both splits (0: features were synthetic)
    fit_peak: int  # MLP fit and test predictions, after the embedding phase
    feature_bytes: int  # bytes of features and targets kept per frame
    embed_s: float
    fit_s: float

    @property
    def peak(self) -> int:
        return max(self.embed_peak, self.fit_peak)


def synthetic_probe_episode(config: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
    """A collector: frames constant within each frame (value from view, episode and time), random state."""
    length, h, w = int(config["episode_length"]), int(config["height"]), int(config["width"])
    views = len(config["cameras"])
    frames = np.empty((views, length, h, w, 3), dtype=np.uint8)
    t = np.arange(length)
    for v in range(views):
        frames[v] = ((v * 101 + index * 7 + t) % 256).astype(np.uint8)[:, None, None, None]
    rng = np.random.default_rng([int(config["seed"]), index])
    return {"frames": frames, "state": rng.normal(size=(length, 4)),
            "action": rng.uniform(-1, 1, size=(length, 1)).astype(np.float32)}


def write_dataset(datasets_dir: Path, train: int, test: int, length: int, size: int) -> Path:
    """A synthetic two-view dataset in the real chunk format; returns its folder."""
    from mftcn_bench.data.dataset import ensure_dataset

    config = {"name": "probe-rss", "cameras": PROBE_CAMERAS, "height": size, "width": size,
              "train_episodes": train, "test_episodes": test, "episode_length": length, "seed": 0}
    return ensure_dataset(datasets_dir, config, synthetic_probe_episode, show_progress=False).root


def subset(root: Path, train: int, test: int, dest: Path) -> Path:
    """A dataset folder holding the first `train` and `test` episodes of `root` (chunks linked, not copied)."""
    manifest = json.loads((root / "manifest.json").read_text())
    chunks = ([c for c in manifest["chunks"] if c["split"] == "train"][:train]
              + [c for c in manifest["chunks"] if c["split"] == "test"][:test])
    dest.mkdir(parents=True, exist_ok=True)
    for chunk in chunks:
        link = dest / chunk["file"]
        if not link.exists():
            link.symlink_to((root / chunk["file"]).resolve())
    config = {**manifest["config"], "train_episodes": train, "test_episodes": test}
    (dest / "manifest.json").write_text(json.dumps({**manifest, "config": config, "chunks": chunks}))
    return dest


def _peak_rss() -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def _reset_peak_rss() -> None:
    with open("/proc/self/clear_refs", "w") as refs:
        refs.write("5")


def _probe_task(encoder_name: str, height: int, width: int, overrides: Sequence[tuple[str, Any]] = ()):
    from mftcn_bench.run.plan import RunRequest, prepare

    return prepare(RunRequest(encoder_name, "cartpole-probe", "paper", 0,
                              (("task.dataset.height", height), ("task.dataset.width", width), *overrides)))


def _run_phases(task, encoder, dataset) -> ProbeMemory:
    """`task.evaluate` with the peak RSS read (and reset) after both splits' features, and at the end."""
    splits_done: list[str] = []
    marks: dict[str, float] = {"start": time.monotonic()}
    peaks: dict[str, int] = {}
    kept: list[int] = []
    features = task.features

    def recorded(enc, data, split):  # the task's own features(); the phase ends after the test split
        x, y, episodes = features(enc, data, split)
        splits_done.append(split)
        kept.append(x.nbytes + y.nbytes + episodes.nbytes)
        if len(splits_done) == 2:
            peaks["embed"] = _peak_rss()
            marks["embedded"] = time.monotonic()
            _reset_peak_rss()
        return x, y, episodes

    task.features = recorded
    result = task.evaluate(encoder, dataset)
    peaks["fit"] = _peak_rss()
    frames = int(result.metrics["train_frames"] + result.metrics["test_frames"])
    return ProbeMemory(frames, peaks["embed"], peaks["fit"], sum(kept) // frames, marks["embedded"] - marks["start"],
                       time.monotonic() - marks["embedded"])


def measure_embedding(root: Path, encoder_name: str = "mftcn4") -> ProbeMemory:
    """Run `cartpole-probe` (paper preset at the dataset's image size, an untrained `encoder_name`) on the
    dataset at `root` in this process; the peak RSS of the embedding phase and of the fit phase. As in a
    run, an encoder on a frozen base first gets its feature cache (built here, beside the dataset, so the
    build's peak counts in the embedding phase) and embeds from it."""
    import torch

    from mftcn_bench.core.home import BenchHome
    from mftcn_bench.data.dataset import MultiViewDataset
    from mftcn_bench.run.artifacts import attach_feature_cache
    from mftcn_bench.run.construct import construct_encoder

    torch.set_num_threads(1)
    dataset = MultiViewDataset(root)
    height, width = dataset.image_shape
    prepared = _probe_task(encoder_name, height, width)
    encoder = construct_encoder(prepared.encoder_entry, prepared.config["encoder"], 0, (height, width))
    attach_feature_cache(encoder, dataset, BenchHome.resolve(root.parent / f"{root.name}-home"), show_progress=False)
    return _run_phases(prepared.task, encoder, dataset)


def measure_fit(train_frames: int, test_frames: int, episode_length: int, epochs: int | None = None,
                encoder_name: str = "mftcn4") -> ProbeMemory:
    """The probe's fit phase at `train_frames` + `test_frames`: `CartpoleProbe.evaluate` with `features`
    giving per-episode arrays of the real shapes and dtypes (concatenated as the task does); `epochs`
    caps the MLP's epochs (None: the paper preset's)."""
    from mftcn_bench.core.registry import get
    from mftcn_bench.data.cartpole import state_targets
    from mftcn_bench.tasks.probe import probe_features

    dim = get("encoders", encoder_name).spec.embedding_dim
    overrides = () if epochs is None else (("task.probe.epochs", epochs),)
    task = _probe_task(encoder_name, 160, 160, overrides).task
    rng = np.random.default_rng(0)

    def synthetic(enc, data, split):
        total = train_frames if split == "train" else test_frames
        xs, ys, names = [], [], []
        for start in range(0, total, episode_length):
            length = min(episode_length, total - start)
            xs.append(probe_features(rng.standard_normal((length, dim)).astype(np.float32)))
            ys.append(state_targets(rng.normal(size=(length, 4))))
            names.append(np.full(length, start // episode_length))
        return np.concatenate(xs), np.concatenate(ys), np.concatenate(names)

    task.features = synthetic
    memory = _run_phases(task, None, None)
    return ProbeMemory(memory.frames, 0, memory.fit_peak, memory.feature_bytes, 0.0, memory.fit_s)


def in_child(*args: str, timeout: float = 7200.0) -> ProbeMemory:
    """`main(args)` in a fresh Python process (one thread per library), so the peak is that phase's own."""
    env = {**os.environ, **dict.fromkeys(THREAD_VARS, "1")}
    done = subprocess.run([sys.executable, "-m", "mftcn_bench.perf.bench_probe", *args], capture_output=True,
                          text=True, env=env, timeout=timeout)
    if done.returncode != 0:
        raise RuntimeError(f"probe memory child failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return ProbeMemory(**json.loads(done.stdout.strip().splitlines()[-1]))


def embedding_growth(embedding: Sequence[ProbeMemory]) -> float:
    """Bytes the embedding phase's peak grows by per frame probed: the features kept (`feature_bytes`), or
    the measured growth between the smallest and the largest run if that is more (allocator
    fragmentation grows with the number of episodes too)."""
    small, large = min(embedding, key=lambda m: m.frames), max(embedding, key=lambda m: m.frames)
    measured = (large.embed_peak - small.embed_peak) / (large.frames - small.frames) if large.frames > small.frames \
        else 0.0
    return max(float(large.feature_bytes), measured)


def paper_scale_peak(embedding: Sequence[ProbeMemory], fit: ProbeMemory, frames: int) -> float:
    """Peak RSS (bytes) of the whole probe at `frames`: the fit phase as measured (at that size), or the
    embedding phase's peak in its largest run plus `embedding_growth` for the frames it did not probe,
    whichever is larger."""
    large = max(embedding, key=lambda m: m.frames)
    return float(max(fit.fit_peak, large.embed_peak + (frames - large.frames) * embedding_growth(embedding)))


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if args[0] == "embed":
        memory = measure_embedding(Path(args[1]), *args[2:3])
    elif args[0] == "fit":
        train, test, length = (int(a) for a in args[1:4])
        memory = measure_fit(train, test, length, int(args[4]) if len(args) > 4 else None)
    else:
        raise SystemExit("usage: python -m mftcn_bench.perf.bench_probe embed ROOT [ENCODER] | "
                         "fit TRAIN TEST LENGTH [EPOCHS]")
    print(json.dumps(asdict(memory)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
