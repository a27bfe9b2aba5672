"""The training figures: mfTCN5's trainer against a naive one, its head on the feature cache against the
end-to-end small-cnn mfTCN5, and the dataset's read speed against what the trainer consumes.

Each times the trainer's steps from its own progress calls (`steps_block`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mftcn_bench.perf.fixtures import cartpole_dataset, mftcn5, train_config
from mftcn_bench.perf.timing import BenchRow, Sizes, Target, alternate, one_thread, steps_block, timed


def _trainer(encoder, dataset, workdir: Path, steps: int, naive: bool) -> Callable[[Any], None]:
    """The harness's `train_multiview`, or the naive trainer: the same batches, loss and Adam, but every clip
    through the network on its own (base CNN on each of its frames, then the head)."""
    import torch

    from mftcn_bench.encoders.base import FitBudget
    from mftcn_bench.encoders.losses import multiview_npairs_loss
    from mftcn_bench.encoders.sampling import plan_batch
    from mftcn_bench.encoders.training import gather_clips, run_training, train_multiview

    config = train_config(encoder, dataset)
    spec, net = encoder.spec, encoder.net
    min_gap = max(config.alpha, spec.lookback)

    def naive_loss(pool, rng: np.random.Generator):
        lengths = {i: ep.length for i, ep in pool.episodes.items()}
        plan = plan_batch(rng, sorted(pool.episodes), lengths, config.batch_timesteps,
                          config.episodes_per_batch, min_gap)
        clips = gather_clips(pool, plan.episodes, plan.times, spec.frames, spec.stride)
        views, count = clips.shape[:2]
        batch = torch.from_numpy(clips.reshape(views * count, *clips.shape[2:])).permute(0, 1, 4, 2, 3)
        embeddings = torch.cat([net(clip[None]) for clip in batch]).reshape(views, count, -1)
        return multiview_npairs_loss(embeddings, config.reg_lambda), {}

    def train(progress) -> None:
        budget = FitBudget(steps=steps)
        workdir.mkdir(parents=True, exist_ok=True)
        if naive:
            run_training(net, dataset, config, budget, progress, workdir, seed=0, batch_loss=naive_loss)
        else:
            train_multiview(net, dataset, config, budget, progress, workdir, frames=spec.frames,
                            stride=spec.stride, seed=0)

    return train


def bench_training(sizes: Sizes, workdir: Path) -> BenchRow:
    """Clips/s of mfTCN5's trainer (`train_multiview`: n-pairs batches of 32 time steps x 2 views) against
    a naive trainer that runs each clip through the network separately."""
    one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    ours, naive = mftcn5(dataset), mftcn5(dataset)
    clips = train_config(ours, dataset).batch_timesteps * len(dataset.cameras)
    steps = sizes.train_steps + 1
    rates = alternate({"ours": steps_block(_trainer(ours, dataset, workdir / "ours", steps, False), steps, clips),
                       "naive": steps_block(_trainer(naive, dataset, workdir / "naive", steps, True), steps, clips)},
                      sizes.rounds, warmup=False)
    return BenchRow("encoder training, mfTCN5 (96x48, 64 clips a step)", rates["ours"], "clips/s",
                    "naive: each clip separately", rates["naive"], rates["ours"] / rates["naive"],
                    Target("report"), "n-pairs clips never share frames (time steps >= lookback apart)")


def bench_head_training(sizes: Sizes, workdir: Path) -> BenchRow:
    """Steps/s of mfTCN5's head trained on the feature cache against today's end-to-end small-cnn mfTCN5."""
    from dataclasses import replace

    from mftcn_bench.core.registry import get
    from mftcn_bench.encoders.feature_cache import ensure_feature_cache
    from mftcn_bench.encoders.mftcn import MfTCNEncoder

    one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    head = mftcn5(dataset)
    base = head.frozen_base()
    head.use_feature_cache(ensure_feature_cache(workdir / "features-head", dataset, base, base.identity(),
                                                show_progress=False))
    spec = get("encoders", "mftcn5").spec
    small = replace(spec, model={**spec.model, "base": {"name": "small-cnn"}})
    scratch = MfTCNEncoder(small, image_shape=dataset.image_shape, seed=0)
    steps = sizes.train_steps + 1

    def trainer(encoder, folder: str) -> Callable[[Any], None]:
        from mftcn_bench.encoders.base import FitBudget
        from mftcn_bench.encoders.training import train_multiview

        config = train_config(encoder, dataset)

        def train(progress) -> None:
            (workdir / folder).mkdir(parents=True, exist_ok=True)
            train_multiview(encoder.net, dataset, config, FitBudget(steps), progress, workdir / folder,
                            frames=encoder.spec.frames, stride=encoder.spec.stride, seed=0,
                            features=encoder.training_features())
        return train

    rates = alternate({"head": steps_block(trainer(head, "head"), steps, 1),
                       "scratch": steps_block(trainer(scratch, "scratch"), steps, 1)}, sizes.rounds, warmup=False)
    return BenchRow("head training on the feature cache, mfTCN5 (96x48, 64 clips a step)", rates["head"],
                    "steps/s", "end-to-end small-cnn mfTCN5", rates["scratch"], rates["head"] / rates["scratch"],
                    Target("report"), "the head reads cached base features; small-cnn decodes frames and "
                    "trains its CNN")


def bench_dataset_read(sizes: Sizes, workdir: Path) -> BenchRow:
    """Frames/s decoded from dataset chunks (every view, checksum checked, no cache) against the frames/s
    the mfTCN5 trainer's batches consume (clips/s x frames per clip), measured alternately."""
    from mftcn_bench.data.dataset import MultiViewDataset

    one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    uncached = MultiViewDataset(dataset.root, cache_episodes=0)
    episodes = uncached.episodes("train") + uncached.episodes("test")
    frames = sum(uncached.episode_length(i) for i in episodes) * len(uncached.cameras)
    encoder = mftcn5(dataset)
    clips = train_config(encoder, dataset).batch_timesteps * len(dataset.cameras)
    steps = sizes.train_steps + 1

    def read_all() -> None:
        for i in episodes:
            uncached.load(i)

    rates = alternate({"read": timed(read_all, frames),
                       "train": steps_block(_trainer(encoder, dataset, workdir / "read", steps, False), steps,
                                             clips * encoder.spec.frames)}, sizes.rounds, warmup=False)
    return BenchRow("dataset read (96x48 chunks, 2 views)", rates["read"], "frames/s",
                    "mfTCN5 trainer's consumption", rates["train"], rates["read"] / rates["train"], Target(">=", 2),
                    "the trainer reloads one pool episode every 10 steps; consumption counts every clip frame")
