"""The device path on a GPU: skipped where torch sees no CUDA device (CI, the project's machines);
`scripts/device-check.sh` runs it on a lent GPU machine. Each test compares the GPU with the CPU on the same
inputs: a GPU's kernels sum in other orders, so equality is within float tolerance, not bitwise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="needs a CUDA GPU: torch.cuda.is_available() is False on this machine")

CUDA = torch.device("cuda:0")


def _data(tmp_path):
    from mftcn_bench.data.dataset import ensure_dataset
    from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config

    def noisy(config, index):
        arrays = synthetic_collector(config, index)
        arrays["frames"] = arrays["frames"] // 2 + np.random.default_rng(index).integers(
            0, 60, arrays["frames"].shape, dtype=np.uint8)
        return arrays

    return ensure_dataset(tmp_path / "d", synthetic_config(height=48, width=96, episode_length=40), noisy,
                          show_progress=False)


# mftcn5's training at a size 40-frame synthetic episodes can hold (as the smoke preset's).
SMALL_TRAIN = {"batch_timesteps": 8, "episodes_per_batch": 2, "alpha": 4, "episode_pool": 3, "checkpoint_every": 1}


def _mftcn(seed: int = 0):
    from dataclasses import replace

    from mftcn_bench.core.registry import get

    entry = get("encoders", "mftcn5")
    spec = replace(entry.spec, train={**entry.spec.train, **SMALL_TRAIN})
    return entry.load()(spec, image_shape=(48, 96), seed=seed)


@pytest.fixture(autouse=True)
def full_float32():
    """GPU against CPU in full float32: TF32 convolutions would round to 10 mantissa bits."""
    from mftcn_bench.core.device import full_float32

    with full_float32():
        yield


def test_resolve_names_the_gpu():
    from mftcn_bench.core.device import resolve_device

    placement = resolve_device("auto")
    assert placement.device == "cuda:0" and placement.gpu == torch.cuda.get_device_name(0)
    assert placement.identity()["gpu"] == placement.gpu


def test_embedding_streaming_and_cache_on_the_gpu_equal_the_cpu(tmp_path):
    from mftcn_bench.core.device import Placement
    from mftcn_bench.encoders.feature_cache import ensure_feature_cache

    data = _data(tmp_path)
    frames = data.load(data.episodes("test")[0]).frames[0]
    cpu, gpu = _mftcn(), _mftcn()
    gpu.to_device(CUDA)
    reference = cpu.embed_episode(frames)
    assert np.allclose(gpu.embed_episode(frames), reference, atol=1e-3)
    stream = gpu.streaming(1)
    pushed = np.concatenate([stream.push(frames[t:t + 1], np.array([t == 0])) for t in range(len(frames))])
    assert np.allclose(pushed, reference, atol=1e-3)
    base = gpu.frozen_base()
    cache = ensure_feature_cache(tmp_path / "f", data, base, base.identity(), show_progress=False,
                                 placement=Placement("cuda:0", gpu=torch.cuda.get_device_name(0)))
    assert cache.manifest["device"]["device"] == "cuda:0"
    gpu.use_feature_cache(cache)
    assert np.allclose(gpu.embed_episode(frames), reference, atol=1e-3)


def test_training_on_the_gpu_follows_the_cpu_and_its_checkpoint_loads_on_the_cpu(tmp_path):
    from mftcn_bench.encoders.base import FitBudget

    data = _data(tmp_path)
    losses: dict[str, list[float]] = {"cpu": [], "gpu": []}
    cpu, gpu = _mftcn(), _mftcn()
    gpu.to_device(CUDA)
    cpu.fit(data, FitBudget(3), lambda s, t, st: losses["cpu"].append(st["loss"]), tmp_path / "c")
    gpu.fit(data, FitBudget(3), lambda s, t, st: losses["gpu"].append(st["loss"]), tmp_path / "g")
    assert np.allclose(losses["cpu"], losses["gpu"], atol=1e-3)
    # A killed GPU fit resumes from its checkpoint (CUDA random state restored from CUDA tensors).
    resumed = _mftcn()
    resumed.to_device(CUDA)
    resumed.fit(data, FitBudget(2), lambda *a: None, tmp_path / "r")  # leaves the step-1 checkpoint
    again: list[float] = []
    resumed.fit(data, FitBudget(3), lambda s, t, st: again.append(st["loss"]), tmp_path / "r")
    assert np.allclose(again, losses["gpu"][1:], atol=1e-3)
    gpu.save(tmp_path / "m.pt")
    loaded = _mftcn(seed=1)
    loaded.load(tmp_path / "m.pt")  # onto the CPU: map_location
    frames = data.load(data.episodes("test")[0]).frames[0]
    assert np.allclose(loaded.embed_episode(frames), gpu.embed_episode(frames), atol=1e-3)


def test_smoke_runs_on_cuda_record_the_gpu(tmp_path):
    from mftcn_bench.cli import main
    from mftcn_bench.results.store import ResultStore

    home = tmp_path / "home"
    for task in ("cartpole-probe", "swingup"):
        assert main(["run", "--encoder", "mftcn5", "--task", task, "--preset", "smoke", "--device", "cuda",
                     "--no-progress", "--home", str(home)]) == 0
    for record in ResultStore(home / "results.sqlite").query():
        assert record.config["device"]["gpu"] == torch.cuda.get_device_name(0)
        assert record.config["fit"]["device"] == "cuda:0"
