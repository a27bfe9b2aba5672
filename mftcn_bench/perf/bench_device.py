"""`mftcn-bench bench --device D`: the same work on device D against the CPU, in one process.

Each figure alternates blocks on the device and on the CPU (`timing.alternate`), so the ratio is the
device's speed-up for that step of the pipeline: the frozen base's forward pass (what builds a feature
cache and what every rollout frame costs), mfTCN5's head training on the cache, and PPO collection on true
state and on streaming mfTCN5 embeddings (environments and rendering on the CPU either way). With
`--device cpu` both sides are the CPU (ratio about 1): the figure then checks the device path itself. GPU
timings synchronise before a block ends, so queued kernels are counted.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from mftcn_bench.core.device import Placement
from mftcn_bench.perf.collection import collect, suite_collector
from mftcn_bench.perf.fixtures import cartpole_dataset, mftcn5, train_config
from mftcn_bench.perf.timing import BenchRow, Sizes, Target, alternate, one_thread, steps_block


def _synchronised(fn: Callable[[], Any], device) -> Callable[[], Any]:
    import torch

    def run() -> Any:
        out = fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return out

    return run


def bench_device(sizes: Sizes, workdir: Path, placement: Placement) -> list[BenchRow]:
    """Rows of device-against-CPU figures for `placement`'s device."""
    import numpy as np
    import torch

    from mftcn_bench.encoders.base import FitBudget
    from mftcn_bench.encoders.feature_cache import base_features, ensure_feature_cache
    from mftcn_bench.encoders.training import train_multiview

    one_thread()
    device, cpu = placement.torch_device, torch.device("cpu")
    name = placement.gpu or placement.device
    dataset = cartpole_dataset(workdir, sizes)
    views = [dataset.load(i).frames for i in dataset.episodes("train")]
    frames = sum(v.shape[0] * v.shape[1] for v in views)
    encoders = {"device": mftcn5(dataset), "cpu": mftcn5(dataset)}
    encoders["device"].to_device(device)

    def forward(where) -> Callable[[], tuple[float, float]]:
        import time

        base = encoders["device" if where is device else "cpu"].frozen_base()

        def block() -> tuple[float, float]:
            began = time.perf_counter()
            _synchronised(lambda: [np.stack([base_features(base, v, 64, where) for v in ep]) for ep in views],
                          where)()
            return float(frames), time.perf_counter() - began
        return block

    rows = []
    rates = alternate({"device": forward(device), "cpu": forward(cpu)}, sizes.rounds)
    rows.append(BenchRow(f"base forward, EfficientNet-Lite0 to block 10 (96x48) on {name}", rates["device"],
                         "frames/s", "the same on the CPU", rates["cpu"], rates["device"] / rates["cpu"],
                         Target("report"), "what a feature-cache build and every rollout frame cost"))

    cpu_base = encoders["cpu"].frozen_base()
    cache = ensure_feature_cache(workdir / "features-device", dataset, cpu_base, cpu_base.identity(),
                                 show_progress=False)
    steps = sizes.train_steps + 1

    def trainer(key: str, where) -> Callable[[Any], None]:
        encoder = encoders[key]
        encoder.use_feature_cache(cache)
        config = train_config(encoder, dataset)

        def train(progress) -> None:
            folder = workdir / f"head-{key}"
            folder.mkdir(parents=True, exist_ok=True)
            train_multiview(encoder.net, dataset, config, FitBudget(steps), _synchronised_progress(progress, where),
                            folder, frames=encoder.spec.frames, stride=encoder.spec.stride, seed=0,
                            features=encoder.training_features(), device=where)
        return train

    rates = alternate({"device": steps_block(trainer("device", device), steps, 1),
                       "cpu": steps_block(trainer("cpu", cpu), steps, 1)}, sizes.rounds, warmup=False)
    rows.append(BenchRow(f"head training on the feature cache, mfTCN5 on {name}", rates["device"], "steps/s",
                         "the same on the CPU", rates["cpu"], rates["device"] / rates["cpu"], Target("report"),
                         "64 clips a step; cached features copied to the device each step"))

    for encoder, label, agent_steps in (("true-state", "true state", sizes.ppo_state_steps),
                                        ("mftcn5", "mfTCN5 embeddings (96x48)", sizes.ppo_pixel_steps)):
        rates = collect({"device": suite_collector(encoder, sizes, agent_steps, device=device),
                         "cpu": suite_collector(encoder, sizes, agent_steps, device=cpu)}, sizes)
        rows.append(BenchRow(f"PPO collection on {label}, policy on {name} ({sizes.ppo_envs} envs)",
                             rates["device"], "frames/s", "the same on the CPU", rates["cpu"],
                             rates["device"] / rates["cpu"], Target("report"),
                             "environments and rendering on the CPU; the encoder's stream and the policy on the "
                             "device"))
    return rows


def _synchronised_progress(progress, device):
    """A trainer's progress callback that waits for the device first (its time stamps time the steps)."""
    import torch

    def report(*args) -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        progress(*args)

    return report
