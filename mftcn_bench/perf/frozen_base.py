"""The frozen base's figures: building the feature cache against the base's forward alone, and the base on
the specs' engine against eager PyTorch."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from mftcn_bench.perf.fixtures import cartpole_dataset, mftcn5
from mftcn_bench.perf.timing import BenchRow, Sizes, Target, alternate, one_thread, timed


def bench_feature_cache(sizes: Sizes, workdir: Path) -> BenchRow:
    """Frames/s of building the per-frame feature cache (decode, base forward, write, checksum) against the
    base's forward pass alone on the same frames."""
    import shutil

    from mftcn_bench.encoders.feature_cache import base_features, ensure_feature_cache

    one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    base = mftcn5(dataset).frozen_base()
    episodes = dataset.episodes("train") + dataset.episodes("test")
    frames = sum(dataset.episode_length(i) for i in episodes) * len(dataset.cameras)
    views = [dataset.load(i).frames for i in episodes]

    def build() -> None:
        shutil.rmtree(workdir / "features", ignore_errors=True)
        ensure_feature_cache(workdir / "features", dataset, base, base.identity(), show_progress=False)

    def forward() -> None:
        for episode in views:
            np.stack([base_features(base, view, 64) for view in episode])

    rates = alternate({"cache": timed(build, frames), "forward": timed(forward, frames)}, sizes.rounds)
    return BenchRow("feature-cache build, EfficientNet-Lite0 to block 10 (96x48, 2 views)", rates["cache"],
                    "frames/s", "the base's forward alone", rates["forward"], rates["cache"] / rates["forward"],
                    Target(">=", 0.8), "decode, forward, write and checksum every frame of every view")


ENGINE_BATCH = 32  # frames a rollout step embeds at once: one per environment of swingup's [ppo] num_envs


def bench_base_engine(sizes: Sizes) -> list[BenchRow]:
    """Frames/s of the frozen base (mfTCN5's `[model.base]`, its engine) against the same base in eager
    PyTorch, at the two swing-up image sizes, a rollout step's batch of frames."""
    from dataclasses import replace

    import torch

    from mftcn_bench.core.registry import get
    from mftcn_bench.encoders.bases import BaseConfig, build_base

    one_thread()
    config = BaseConfig(**get("encoders", "mftcn5").spec.model["base"])
    bases = {"engine": build_base(config), "eager": build_base(replace(config, engine="torch"))}
    rows = []
    for height, width in ((48, 96), (160, 160)):
        images = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (ENGINE_BATCH, 3, height, width),
                                                                    dtype=np.uint8))
        repeat = max(1, sizes.embed_frames // ENGINE_BATCH)

        def forward(base, images=images, repeat=repeat) -> Callable[[], None]:
            return lambda: [base(images) for _ in range(repeat)]

        rates = alternate({name: timed(forward(base), repeat * ENGINE_BATCH) for name, base in bases.items()},
                          sizes.rounds)
        rows.append(BenchRow(f"frozen base forward, {config.engine} ({width}x{height}, batch {ENGINE_BATCH})",
                             rates["engine"], "frames/s", "eager PyTorch", rates["eager"],
                             rates["engine"] / rates["eager"], Target("report"),
                             f"EfficientNet-Lite0 to block {config.layer}, one thread"))
    return rows
