"""What several figures share: the tasks as a run prepares them, the rendered cartpole dataset and mfTCN5.

The dataset is collected once into the benchmark's work folder and reused by every figure that reads it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mftcn_bench.perf.timing import Sizes


def control_task(task: str, encoder: str, overrides: Sequence[tuple[str, Any]] = ()):
    """The task `task` as a run of `encoder` (paper preset, seed 0) prepares it."""
    from mftcn_bench.run.plan import RunRequest, prepare

    return prepare(RunRequest(encoder, task, "paper", 0, tuple(overrides))).task


def cartpole_dataset(workdir: Path, sizes: Sizes):
    """A rendered multi-view cartpole dataset (the probe's 96x48 data at `sizes`), collected once into
    `workdir` and reused by the figures that read it."""
    from mftcn_bench.data.cartpole import collect_episode
    from mftcn_bench.data.dataset import ensure_dataset

    config = dict(control_task("cartpole-probe", "mftcn5").dataset_config)
    config.update(train_episodes=sizes.data_train, test_episodes=1, episode_length=sizes.data_length)
    return ensure_dataset(workdir / "datasets", config, collect_episode, show_progress=False)


def mftcn5(dataset, seed: int = 0):
    """A fresh mfTCN5 encoder for `dataset`'s image shape."""
    from mftcn_bench.core.registry import get
    from mftcn_bench.encoders.mftcn import MfTCNEncoder

    return MfTCNEncoder(get("encoders", "mftcn5").spec, image_shape=dataset.image_shape, seed=seed)


def train_config(encoder, dataset):
    """The encoder's training settings without checkpoints (they would be timed) and with an episode pool
    no larger than the benchmark's small dataset."""
    from dataclasses import replace

    return replace(encoder.train_config, checkpoint_every=0, episode_pool=min(encoder.train_config.episode_pool,
                                                                           len(dataset.episodes("train"))))
