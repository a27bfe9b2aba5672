"""The device path on the CPU: resolving `--device`, what a run records and keys by, placing encoders and
PPO explicitly on `cpu`, checkpoints that carry CUDA random state and load with `map_location`. The same
paths on a GPU are in test_cuda.py (skipped without one); refusals are in test_bad_inputs.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mftcn_bench.cli import main
from mftcn_bench.core import device as devices
from mftcn_bench.core.device import CPU, DevicePlaced, Placement, requested_device, resolve_device
from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.registry import get
from mftcn_bench.data.synthetic import synthetic_collector
from mftcn_bench.results.store import ResultStore
from mftcn_bench.run.artifacts import place_encoder
from mftcn_bench.run.plan import RunRequest, encoder_key_of, prepare, run_id_of
from tests.test_bad_inputs import TINY_MFTCN, TINY_TASK

GPU = Placement("cuda:0", gpu="NVIDIA H200", cuda="12.8", cudnn=91000)


def test_names_resolve_on_a_cpu_machine(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == CPU and resolve_device(" CPU ") == CPU
    assert resolve_device("cpu", deterministic=True).deterministic
    for bad in ("gpu", "cuda:", "cuda:-1", "mps", ""):
        with pytest.raises(BenchError, match="unknown device"):
            resolve_device(bad)
    with pytest.raises(BenchError, match="sees no CUDA GPU"):
        resolve_device("cuda")


def test_the_flag_wins_over_the_environment(monkeypatch):
    monkeypatch.delenv(devices.ENV_VAR, raising=False)
    assert requested_device(None) == "auto"
    monkeypatch.setenv(devices.ENV_VAR, "cpu")
    assert requested_device(None) == "cpu" and requested_device("cuda:1") == "cuda:1"


def test_identity_names_the_gpu_not_its_index():
    assert CPU.identity() == {"device": "cpu"} and Placement("cpu", deterministic=True).identity() == CPU.identity()
    other_index = Placement("cuda:3", gpu=GPU.gpu, cuda=GPU.cuda, cudnn=GPU.cudnn)
    assert GPU.identity() == other_index.identity()
    assert GPU.identity() != Placement("cuda:0", gpu="NVIDIA A100", cuda="12.8").identity()
    assert GPU.identity() != Placement("cuda:0", gpu=GPU.gpu, cuda=GPU.cuda, deterministic=True).identity()
    assert GPU.record()["gpu"] == "NVIDIA H200"


def test_a_gpu_run_never_shares_an_id_or_an_encoder_with_a_cpu_run(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    prepared = prepare(RunRequest("mftcn1", "cartpole-probe", "smoke", 0, device="cpu"))
    on_gpu = prepared.__class__(**{**prepared.__dict__, "placement": GPU})
    assert run_id_of(prepared, "fp") != run_id_of(on_gpu, "fp")
    assert encoder_key_of(prepared, "fp") != encoder_key_of(on_gpu, "fp")
    from mftcn_bench.core import identity

    # The CPU is the reference: its ids are those computed without a placement.
    assert run_id_of(prepared, "fp") == identity.run_id(prepared.config, prepared.preset, 0, "fp", prepared.code,
                                                          base=prepared.base)


def test_built_in_encoders_that_can_move_declare_it():
    for name in ("mftcn5", "tcn", "shuffle-and-learn", "lite0-features", "pve", "pixels-cnn"):
        entry = get("encoders", name)
        encoder = entry.load()(entry.spec, image_shape=(48, 96), seed=0)
        assert isinstance(encoder, DevicePlaced), name
        assert place_encoder(encoder, CPU) == CPU and encoder.device == torch.device("cpu")


def test_encoders_without_a_network_stay_on_the_cpu():
    for name in ("true-state", "random-state"):
        entry = get("encoders", name)
        assert not isinstance(entry.load()(entry.spec, image_shape=(48, 96), seed=0), DevicePlaced), name


def test_an_encoder_without_to_device_stays_on_the_cpu():
    class Plain:
        pass

    assert place_encoder(Plain(), GPU) == CPU  # type: ignore[arg-type]


def test_explicit_cpu_run_records_its_device(capsys, tmp_path, monkeypatch):
    monkeypatch.setattr("mftcn_bench.tasks.probe.collect_episode", synthetic_collector)
    home = tmp_path / "home"
    assert main(["run", *TINY_MFTCN, "--device", "cpu", "--deterministic", "--home", str(home)]) == 0
    assert not torch.are_deterministic_algorithms_enabled(), "the run's settings end with the run"
    (record,) = ResultStore(home / "results.sqlite").query()
    assert record.config["device"] == {"device": "cpu", "gpu": None, "cuda": None, "cudnn": None,
                                       "deterministic": True}
    assert record.config["fit"]["device"] == "cpu"
    # The same run asked for by `auto` on this CPU machine is the same run.
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["run", *TINY_MFTCN, "--device", "auto", "--home", str(home)]) == 0
    assert "reused stored result" in capsys.readouterr().out
    assert main(["run", "--encoder", "random-state", *TINY_TASK, "--device", "cpu", "--home", str(home)]) == 0


def test_training_checkpoints_keep_the_cuda_random_state_and_load_with_map_location(tmp_path):
    from mftcn_bench.data.dataset import ensure_dataset
    from mftcn_bench.data.synthetic import synthetic_config
    from mftcn_bench.encoders.base import FitBudget
    from mftcn_bench.encoders.mftcn import MfTCNEncoder

    data = ensure_dataset(tmp_path / "d", synthetic_config(height=16, width=24, episode_length=30),
                          synthetic_collector, show_progress=False)
    model = {"adapter_channels": 4, "temporal_channels": 4, "base": {"name": "small-cnn", "channels": [4],
                                                                     "kernels": [3], "strides": [2]}}
    train = {"steps": 2, "batch_timesteps": 4, "episodes_per_batch": 2, "alpha": 2, "lr": 1e-3,
             "weight_decay": 0.0, "reg_lambda": 0.0, "episode_pool": 2, "pool_refresh_steps": 0,
             "checkpoint_every": 1}
    from mftcn_bench.core.specs import EncoderSpec

    encoder = MfTCNEncoder(EncoderSpec("t", "mftcn", "t", 2, 1, 4, model, train), image_shape=(16, 24), seed=0)
    encoder.to_device(torch.device("cpu"))
    encoder.fit(data, FitBudget(3), lambda *a: None, tmp_path / "w")  # stops after the step-2 checkpoint
    state = torch.load(tmp_path / "w" / "train_checkpoint.pt", weights_only=True, map_location="cpu")
    saved, now = state["cuda_rng"], devices.cuda_rng_state()  # empty without CUDA, one state per GPU with it
    assert len(saved) == len(now) and all(torch.equal(a.cpu(), b) for a, b in zip(saved, now, strict=True))
    encoder.save(tmp_path / "m.pt")
    again = MfTCNEncoder(encoder.spec, image_shape=(16, 24), seed=1)
    again.load(tmp_path / "m.pt")
    frames = data.load(data.episodes("test")[0]).frames[0]
    assert np.array_equal(again.embed_episode(frames), encoder.embed_episode(frames))


def test_deterministic_holds_for_the_run_only(tmp_path, monkeypatch):
    """`--deterministic` turns torch's deterministic algorithms and full float32 on while the run computes
    and restores every setting after (a sweep's worker or a test process runs on with its own)."""
    import torch

    from mftcn_bench.core.home import BenchHome
    from mftcn_bench.run.runner import run
    from mftcn_bench.tasks.probe import CartpoleProbe

    seen: list[tuple[bool, str]] = []
    evaluate = CartpoleProbe.evaluate

    def recording(self, encoder, dataset, workdir=None):
        seen.append((torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.conv.fp32_precision))
        return evaluate(self, encoder, dataset, workdir)

    monkeypatch.setattr(CartpoleProbe, "evaluate", recording)
    before = (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.conv.fp32_precision,
              torch.backends.cuda.matmul.fp32_precision, torch.backends.cudnn.deterministic)
    tiny = (("task.dataset.episode_length", 30), ("task.dataset.train_episodes", 3), ("task.dataset.test_episodes", 1),
            ("task.dataset.height", 16), ("task.dataset.width", 24), ("task.probe.epochs", 3),
            ("task.probe.hidden", [8]), ("task.probe.batch_size", 16))
    run(RunRequest("true-state", "cartpole-probe", "smoke", 0, tiny, device="cpu", deterministic=True),
        BenchHome.resolve(tmp_path), show_progress=False)
    assert seen == [(True, "ieee")]
    assert (torch.are_deterministic_algorithms_enabled(), torch.backends.cudnn.conv.fp32_precision,
            torch.backends.cuda.matmul.fp32_precision, torch.backends.cudnn.deterministic) == before
