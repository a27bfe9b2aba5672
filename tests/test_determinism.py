"""Determinism: the same command with the same seed, twice on CPU in two empty homes, gives byte-identical
dataset chunks (rendered, not synthetic), bitwise-identical encoder weights and bitwise-identical probe
metrics. What is not deterministic, and why, is in the README ("Determinism")."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from mftcn_bench.cli import main
from mftcn_bench.results.store import ResultStore, RunRecord

# Rendered cartpole: 3 + 1 episodes of 20 frames at 48x24; a small mfTCN trained 6 steps; a small probe.
TASK = ["--task", "cartpole-probe", "--preset", "smoke", "--no-progress",
        "--set", "task.dataset.episode_length=20", "--set", "task.dataset.train_episodes=3",
        "--set", "task.dataset.test_episodes=1", "--set", "task.dataset.height=24", "--set", "task.dataset.width=48",
        "--set", "task.probe.epochs=10", "--set", "task.probe.batch_size=16", "--set", "task.probe.hidden=[32]"]
MFTCN = ["--encoder", "mftcn1", *TASK, "--set", "encoder.train.steps=6", "--set", "encoder.train.checkpoint_every=0",
         "--set", "encoder.model.adapter_channels=8", "--set", "encoder.model.temporal_channels=8",
         "--set", "encoder.train.batch_timesteps=4", "--set", "encoder.train.episodes_per_batch=2",
         "--set", "encoder.train.alpha=4", "--set", "encoder.train.episode_pool=3"]
RANDOM = ["--encoder", "random-state", *TASK]

pytestmark = pytest.mark.slow  # renders its datasets


def run(home: Path, args: list[str], seed: int = 0) -> RunRecord:
    before = {r.run_id for r in ResultStore(home / "results.sqlite").query()} if home.exists() else set()
    assert main(["run", *args, "--seed", str(seed), "--home", str(home)]) == 0
    (record,) = [r for r in ResultStore(home / "results.sqlite").query() if r.run_id not in before]
    return record


def chunks(home: Path) -> dict[str, str]:
    (manifest,) = home.glob("datasets/*/manifest.json")
    return {c["file"]: c["sha256"] for c in json.loads(manifest.read_text())["chunks"]}


def weights(record: RunRecord) -> dict[str, torch.Tensor]:
    return torch.load(record.config["fit"]["checkpoint"], weights_only=True)["model"]


def test_same_seed_twice_gives_identical_data_weights_and_metrics(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    first = [run(a, MFTCN), run(a, RANDOM)]
    second = [run(b, MFTCN), run(b, RANDOM)]
    capsys.readouterr()

    assert chunks(a) == chunks(b) and len(chunks(a)) == 4
    for name in chunks(a):
        assert next(a.glob(f"datasets/*/{name}")).read_bytes() == next(b.glob(f"datasets/*/{name}")).read_bytes()
    wa, wb = weights(first[0]), weights(second[0])
    assert wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)
    for x, y in zip(first, second, strict=True):
        assert x.run_id == y.run_id and x.dataset_id == y.dataset_id
        assert json.dumps(x.metrics, sort_keys=True) == json.dumps(y.metrics, sort_keys=True)  # every bit (repr)
        assert x.config["fit"].get("final_loss") == y.config["fit"].get("final_loss")

    # The comparison can fail: another seed gives other weights and other metrics (same data).
    other = run(a, MFTCN, seed=1)
    assert not all(torch.equal(wa[k], weights(other)[k]) for k in wa)
    assert other.metrics["average"] != first[0].metrics["average"]
    capsys.readouterr()
