"""Pinned experts: a committed expert file is loaded, never trained; the data set recorded from it names its
checksum; `mftcn-bench expert train` makes one on purpose."""

import json

import numpy as np
import pytest
import torch

from mftcn_bench.cli import main
from mftcn_bench.core.errors import TrainingError
from mftcn_bench.core.home import BenchHome
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.rl import expert as experts
from mftcn_bench.run.plan import RunRequest, prepare

CHEETAH_SMOKE = ["cheetah", "--preset", "smoke", "--set", "task.dataset.train_episodes=2",
                 "--set", "task.dataset.test_episodes=1", "--set", "task.dataset.episode_length=20"]


@pytest.fixture
def pinned(tmp_path, monkeypatch):
    """An empty pinned-experts folder of the project (the real one holds the presets' experts)."""
    folder = tmp_path / "pinned"
    folder.mkdir()
    monkeypatch.setattr(experts, "pinned_folder", lambda: folder)
    return folder


def cheetah_task():
    return prepare(RunRequest("mftcn5", "cheetah", "smoke")).task


def collected(home) -> list[MultiViewDataset]:
    return [MultiViewDataset(p) for p in (home / "datasets").glob("cheetah-expert-*") if (p / "manifest.json").exists()]


def test_expert_train_pins_a_file_that_fresh_homes_record_from_without_training(tmp_path, pinned, capsys):
    trainer = tmp_path / "trainer"
    assert main(["expert", "train", "--task", "cheetah", "--preset", "smoke", "--home", str(trainer)]) == 0
    out = capsys.readouterr().out
    expert = cheetah_task().expert
    env, ppo, seed = expert.env, expert.ppo, expert.seed
    path = experts.pinned_path(env, ppo, seed)
    assert path.parent == pinned and f"pinned {path}" in out and "new key" in out
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["sha256"] == experts.file_sha256(path) and sidecar["seed"] == seed
    assert sidecar["ppo"]["frames"] == 320  # the smoke preset's expert settings
    # pinned again without --force: refused before any training
    assert main(["expert", "train", "--task", "cheetah", "--preset", "smoke", "--home", str(trainer)]) == 2
    assert "--force" in capsys.readouterr().err

    homes = [tmp_path / "fresh-a", tmp_path / "fresh-b"]
    for home in homes:
        assert main(["data", "collect", *CHEETAH_SMOKE, "--home", str(home), "--no-progress"]) == 0
        assert not list(BenchHome(home).experts.glob("*/expert.pt"))  # nothing trained in the home
    (first,), (second,) = (collected(home) for home in homes)
    assert first.config["expert"] == f"pinned-{sidecar['sha256'][:16]}"
    assert first.fingerprint == second.fingerprint  # two recordings from one file: the same frames and states


def test_another_expert_file_gives_the_data_another_key_and_a_damaged_one_is_refused(tmp_path, pinned):
    task = cheetah_task()
    env, ppo, seed = task.expert.env, task.expert.ppo, task.expert.seed
    unpinned = dict(task.dataset_config)
    assert unpinned["expert"] == experts.expert_key(env, ppo, seed)  # trained in the home: the training key
    trained = experts.train_expert(tmp_path / "home", env, ppo, seed)
    path = experts.pin_expert(trained, env, ppo, seed)
    first = dict(task.dataset_config)
    assert first["expert"].startswith("pinned-") and first != unpinned
    weights = torch.load(path, weights_only=True)
    for value in weights["nets"].values():
        value.add_(0.01) if value.is_floating_point() else None
    torch.save(weights, path)
    with pytest.raises(TrainingError, match="does not match the checksum"):
        experts.ensure_expert(tmp_path / "home", env, ppo, seed)
    sidecar = json.loads(path.with_suffix(".json").read_text())
    sidecar["sha256"] = experts.file_sha256(path)  # remade on purpose: a new, valid pinned expert
    path.with_suffix(".json").write_text(json.dumps(sidecar))
    second = dict(task.dataset_config)
    assert second["expert"] != first["expert"] and second["expert"].startswith("pinned-")
    from mftcn_bench.data.dataset import dataset_id

    assert dataset_id(first, task.collector) != dataset_id(second, task.collector)
    assert experts.ensure_expert(tmp_path / "home", env, ppo, seed) == path


def test_pinned_demonstrations_render_the_live_recording_without_the_expert_and_key_the_data(tmp_path, pinned,
                                                                                              capsys, monkeypatch):
    from mftcn_bench.rl import demos

    smoke = ["cheetah", "--preset", "smoke", "--no-progress"]
    expert = cheetah_task().expert
    experts.pin_expert(experts.train_expert(tmp_path / "trainer", expert.env, expert.ppo, expert.seed),
                       expert.env, expert.ppo, expert.seed)
    live_config = dict(cheetah_task().dataset_config)
    assert "demos" not in live_config  # no pinned demonstrations yet: recorded by running the expert
    assert main(["data", "collect", *smoke, "--home", str(tmp_path / "live")]) == 0

    assert main(["expert", "demos", "--task", "cheetah", "--preset", "smoke", "--no-progress"]) == 0
    path = demos.pinned_demos(expert, live_config)
    assert path is not None and path.parent == pinned and f"pinned {path}" in capsys.readouterr().out
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["episodes"] == 4 and sidecar["expert"] == live_config["expert"]
    assert main(["expert", "demos", "--task", "cheetah", "--preset", "smoke"]) == 2  # refused without --force
    assert "--force" in capsys.readouterr().err

    def no_expert(*args, **kwargs):
        raise AssertionError("the expert ran although its demonstrations are pinned")

    monkeypatch.setattr(demos, "ExpertPolicy", no_expert)
    assert main(["data", "collect", *smoke, "--home", str(tmp_path / "pinned-home")]) == 0
    (live,), (rendered,) = collected(tmp_path / "live"), collected(tmp_path / "pinned-home")
    assert rendered.config["demos"] == f"pinned-{sidecar['sha256'][:16]}" and rendered.root != live.root
    for episode in range(4):  # the pinned states, set and rendered, give the live recording's bytes
        a, b = live.load(episode), rendered.load(episode)
        for name in ("frames", "state", "action"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"episode {episode} {name}")

    stored = dict(np.load(path))
    stored["qpos"] = stored["qpos"] + 1e-3
    np.savez_compressed(path, **stored)  # another file: refused until its sidecar is remade
    with pytest.raises(TrainingError, match="pinned demonstrations .* does not match the checksum"):
        demos.pinned_demos(expert, live_config)
    sidecar["sha256"] = experts.file_sha256(path)
    path.with_suffix(".json").write_text(json.dumps(sidecar))
    assert cheetah_task().dataset_config["demos"] != rendered.config["demos"]


@pytest.mark.parametrize("task, preset", [("cheetah", "paper"), ("cheetah", "quick"), ("cheetah-difference", "paper"),
                                          ("imitate-cheetah", "paper"), ("imitate-swingup", "paper"),
                                          ("imitate-swingup", "quick")])
def test_the_project_pins_the_demonstrations_of_every_expert_preset(task, preset):
    """Each preset that records the pinned expert renders committed demonstrations: they are named by the
    data set's key and hold every episode and frame it films (`mftcn-bench expert demos`)."""
    from mftcn_bench.rl.demos import pinned_demos

    recorder = prepare(RunRequest("true-state", task, preset)).task
    config = recorder.demos_config
    path = pinned_demos(recorder.expert, config)  # its checksum checked against the sidecar
    assert path is not None and config["demos"] == f"pinned-{experts.file_sha256(path)[:16]}"
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["expert"] == config["expert"] and sidecar["episode_length"] >= config["episode_length"]
    assert sidecar["episodes"] >= config["train_episodes"] + config["test_episodes"]
    with np.load(path) as stored:
        shape = (sidecar["episodes"], sidecar["episode_length"])
        assert stored["qpos"].shape[:2] == stored["qvel"].shape[:2] == stored["action"].shape[:2] == shape
