"""Imitation (`tasks/imitation.py`): behaviour cloning on a frozen embedding from an expert's demonstrations.

The clone's tests stand a hand-written expert in for the PPO one (training PPO to a good policy takes
minutes): a PD controller that holds cartpole-balance's pole up for the whole episode (about 1000), where
random pushes score about 300 and no push about 750. The encoder's own data comes from the synthetic
collector (true-state and random-state never read it).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mftcn_bench.cli import main
from mftcn_bench.core import registry
from mftcn_bench.core.specs import resolve_config
from mftcn_bench.data.synthetic import synthetic_collector
from mftcn_bench.results.store import ResultStore

# cartpole-balance, 5 demonstrations of whole 1000-step episodes, a small clone, 6 test episodes.
BALANCE = ["--task", "imitate-swingup", "--preset", "smoke", "--no-progress", "--set", 'task.env.task="balance"',
           "--set", "task.env.episode_length=1000", "--set", "task.demos.episodes=5",
           "--set", "task.demos.episode_length=125", "--set", "task.bc.demonstrations=5",
           "--set", "task.bc.hidden=[64, 64]", "--set", "task.bc.steps=1500", "--set", "task.bc.batch_size=64",
           "--set", "task.bc.eval_episodes=6", "--set", "task.bc.eval_envs=6"]


class Balancer:
    """The stand-in expert: a PD controller on the pole's angle and the cart's position (`act` on one
    physics state (x, theta, x_dot, theta_dot), as `rl.expert.ExpertPolicy`)."""

    def __init__(self, *args: object) -> None:
        pass

    def act(self, state: np.ndarray) -> np.ndarray:
        x, theta, x_dot, theta_dot = state
        return np.clip([5 * np.sin(theta) + 2 * theta_dot + x + x_dot], -1.0, 1.0)


@pytest.fixture
def stand_in_expert(monkeypatch, tmp_path):
    """No PPO: the expert is `Balancer`, its 'training' counted; the encoder data is synthetic."""
    trained: list[Path] = []

    def ensure_expert(experts_dir, env, ppo, seed, progress=None):
        path = experts_dir / "stand-in" / "expert.pt"
        trained.append(path)
        return path

    monkeypatch.setattr("mftcn_bench.rl.expert.ensure_expert", ensure_expert)
    monkeypatch.setattr("mftcn_bench.rl.expert.ExpertPolicy", Balancer)
    monkeypatch.setattr("mftcn_bench.tasks.imitation.collect_episode", synthetic_collector)
    return trained


def _run(home: Path, encoder: str, seed: int = 0) -> dict[str, float]:
    assert main(["run", "--encoder", encoder, *BALANCE, "--seed", str(seed), "--home", str(home)]) == 0
    [record] = [r for r in ResultStore(home / "results.sqlite").query(encoder=encoder) if r.seed == seed]
    print(encoder, seed, {k: round(v, 4) for k, v in record.metrics.items() if v is not None})
    return record.metrics


@pytest.mark.slow
def test_cloning_true_state_reaches_the_expert_and_random_state_or_shuffled_actions_do_not(
        tmp_path, stand_in_expert, monkeypatch, capsys):
    home = tmp_path / "home"
    true = _run(home, "true-state")
    random = _run(home, "random-state")
    expert = true["expert_return_mean"]
    assert expert > 950 and random["expert_return_mean"] == expert  # one expert, the same initial states
    assert true["fraction_of_expert"] > 0.95, true
    assert random["fraction_of_expert"] < 0.8, random
    assert true["return_mean"] - random["return_mean"] > 200

    # Actions shuffled against the frames: the clone sees the right states and the wrong actions.
    import mftcn_bench.tasks.imitation as imitation

    plain = imitation.demo_rows

    def shuffled(*args, **kwargs):
        x, y = plain(*args, **kwargs)
        return x, y[np.random.default_rng(0).permutation(len(y))]

    monkeypatch.setattr(imitation, "demo_rows", shuffled)
    wrong = _run(home, "true-state", seed=1)
    assert wrong["fraction_of_expert"] < 0.8, wrong
    assert wrong["bc_heldout_mse"] > 2 * true["bc_heldout_mse"]
    assert "fraction of expert" in capsys.readouterr().out


@pytest.mark.slow
def test_demonstrations_are_recorded_once_for_every_encoder_and_the_expert_trained_once(tmp_path, stand_in_expert,
                                                                                       monkeypatch):
    home = tmp_path / "home"
    recorded: list[int] = []
    from mftcn_bench.rl.demos import ExpertDemoCollector

    record = ExpertDemoCollector.__call__

    def counting(self, config, index):
        recorded.append(index)
        return record(self, config, index)

    monkeypatch.setattr(ExpertDemoCollector, "__call__", counting)
    small = ["--set", "task.env.episode_length=80", "--set", "task.demos.episode_length=10",
             "--set", "task.bc.eval_episodes=2", "--set", "task.bc.eval_envs=2", "--set", "task.bc.steps=20"]
    assert main(["run", "--encoder", "true-state", *BALANCE, *small, "--home", str(home)]) == 0
    assert sorted(recorded) == list(range(6))  # 5 demonstrations and 1 held out
    assert main(["run", "--encoder", "random-state", *BALANCE, *small, "--home", str(home)]) == 0
    assert sorted(recorded) == list(range(6)), "the second encoder recorded demonstrations again"
    demos = [p for p in (home / "datasets").glob("cartpole-swingup-expert-*") if p.is_dir()]
    assert len(demos) == 1
    records = ResultStore(home / "results.sqlite").query(task="imitate-swingup")
    assert {r.encoder for r in records} == {"true-state", "random-state"}
    assert len({r.metrics["expert_return_mean"] for r in records}) == 1
    assert len(set(stand_in_expert)) == 1  # one expert (found again, never a second one)


@pytest.mark.slow
def test_a_killed_demonstration_collection_resumes_from_its_finished_episodes(tmp_path, stand_in_expert,
                                                                            monkeypatch):
    home = tmp_path / "home"
    from mftcn_bench.rl.demos import ExpertDemoCollector

    record = ExpertDemoCollector.__call__
    calls: list[int] = []

    def dies_at_the_fourth(self, config, index):
        calls.append(index)
        if len(calls) == 4:
            raise KeyboardInterrupt  # the process killed in the middle of episode 3
        return record(self, config, index)

    monkeypatch.setattr(ExpertDemoCollector, "__call__", dies_at_the_fourth)
    small = ["--set", "task.env.episode_length=80", "--set", "task.demos.episode_length=10",
             "--set", "task.bc.eval_episodes=2", "--set", "task.bc.eval_envs=2", "--set", "task.bc.steps=20"]
    # The command line turns the interrupt into its exit code, keeping what was finished.
    assert main(["run", "--encoder", "true-state", *BALANCE, *small, "--home", str(home)]) != 0
    [root] = [p for p in (home / "datasets").glob("cartpole-swingup-expert-*") if p.is_dir()]
    assert not (root / "manifest.json").exists()
    done = {c["file"]: (root / c["file"]).stat().st_mtime_ns for c in json.loads((root / "progress.json").read_text())}
    assert sorted(done) == [f"ep{i:05d}.npz" for i in range(3)]

    assert main(["run", "--encoder", "true-state", *BALANCE, *small, "--home", str(home)]) == 0
    assert calls[4:] == [3, 4, 5], "the finished episodes were recorded again"
    manifest = json.loads((root / "manifest.json").read_text())
    assert len(manifest["chunks"]) == 6
    assert all((root / name).stat().st_mtime_ns == mtime for name, mtime in done.items())


def test_the_demonstrations_are_the_streams_the_clone_sees_online(stand_in_expert):
    """A recorded demonstration replayed in the clone's environment: random-state's noise is a hash of each
    clip's pixels, so equal embeddings mean pixel-equal frames at the same rate; the actions are the expert's
    at each observation."""
    import torch

    from mftcn_bench.encoders.base import embed_episode
    from mftcn_bench.rl.demos import ExpertDemoCollector
    from mftcn_bench.rl.observation import observed_env
    from mftcn_bench.rl.observers import make_observer
    from mftcn_bench.run.plan import RunRequest, prepare_with_encoder

    request = RunRequest("random-state", "imitate-swingup", "smoke", 0,
                         (("task.env.episode_length", 160), ("task.demos.episode_length", 20),
                          ("task.demos.action_noise", 0.0)))  # replayed: the applied actions
    prepared, encoder = prepare_with_encoder(request)
    assert encoder is not None  # the task names its frame size: the plan constructed the encoder
    task = prepared.task
    expert = Balancer()
    episode = ExpertDemoCollector(None, task.expert.env, task.expert.ppo, policy=expert)(task.demos_config, 0)
    frames, state, action = episode["frames"][0], episode["state"], episode["action"]
    offline = embed_episode(encoder, frames, state)

    env = observed_env(task.env_config, 1, 0, make_observer(encoder, 1), encoder.info.embedding_dim, True)
    td = env.reset()
    physics = env.base_env._envs[0].physics
    with physics.reset_context():  # the demonstration's initial state (the reset's own frame is not compared)
        physics.data.qpos[:], physics.data.qvel[:] = state[0, :2], state[0, 2:]
    for t in range(1, len(state)):
        np.testing.assert_allclose(action[t - 1], expert.act(state[t - 1]))
        td.set("action", torch.from_numpy(action[t - 1][None]).float())
        td = env.step(td)["next"]
        np.testing.assert_array_equal(td.get("observation").numpy()[0], offline[t])
    env.close()


def test_noise_drives_the_recording_and_the_expert_labels_it():
    """DART: with `action_noise` the episode leaves the noiseless one's path, and every recorded action is
    still the expert's own at the recorded state; at 0 the data set's config (its id) carries no noise key."""
    from mftcn_bench.rl.demos import ExpertDemoCollector
    from mftcn_bench.run.plan import RunRequest, prepare

    def episode(noise: float) -> dict[str, np.ndarray]:
        task = prepare(RunRequest("true-state", "imitate-swingup", "smoke", 0,
                                  (("task.demos.episode_length", 40), ("task.demos.action_noise", noise)))).task
        config = task.demos_config
        assert ("action_noise" in config) == (noise > 0)
        return ExpertDemoCollector(None, task.expert.env, task.expert.ppo, policy=Balancer())(config, 0)

    calm, pushed = episode(0.0), episode(0.5)
    np.testing.assert_array_equal(calm["state"][0], pushed["state"][0])  # the same initial state
    assert np.abs(calm["state"][-1] - pushed["state"][-1]).max() > 1e-3
    for recorded in (calm, pushed):
        labels = np.stack([Balancer().act(s) for s in recorded["state"]])
        np.testing.assert_allclose(recorded["action"], labels.astype(np.float32))


@pytest.mark.parametrize("preset", ["smoke", "quick", "paper"])
def test_the_encoder_is_the_matching_ppo_tasks(preset):
    """imitate-swingup trains its encoder on swingup's data with swingup's budget (one fit serves both);
    imitate-cheetah on the cheetah task's expert demonstrations, and clones from that very data set."""
    from mftcn_bench.run.plan import RunRequest, prepare

    for imitate, control in (("imitate-swingup", "swingup"), ("imitate-cheetah", "cheetah")):
        for encoder in ("mftcn5", "true-state"):
            ours = prepare(RunRequest(encoder, imitate, preset, 0))
            theirs = prepare(RunRequest(encoder, control, preset, 0))
            assert ours.config["encoder"] == theirs.config["encoder"]
            assert ours.dataset_key == theirs.dataset_key
    cheetah = prepare(RunRequest("mftcn5", "imitate-cheetah", preset, 0)).task
    assert cheetah.demos_config == dict(cheetah.dataset_config)


BAD = {
    "pixels-cnn": (["--encoder", "pixels-cnn"],
                   ["encoder 'pixels-cnn' is trained with a policy", "use an encoder that embeds frames, true-state "
                    "or random-state"]),
    "more demonstrations than recorded": (["--set", "task.bc.demonstrations=4"],
                                          ["task.bc.demonstrations (4) is more than the demonstrations recorded, "
                                           "task.demos.episodes (3)"]),
    "no test episodes": (["--set", "task.bc.eval_episodes=0"], ["task.bc.eval_episodes must be >= 1, got 0"]),
    "policy camera not filmed": (["--set", 'task.demos.cameras=["lookatcart"]'],
                                 ["[demos] cameras ['lookatcart'] must hold the policy's camera"]),
    "negative noise": (["--encoder", "true-state", "--set", "task.demos.action_noise=-0.1"],
                       ["task.demos.action_noise must be a number >= 0", "got -0.1"]),
    "noise on the encoder's own data": (["--encoder", "true-state", "--task", "imitate-cheetah", "--set",
                                         "task.demos.action_noise=0.2"],
                                        ["task.demos.action_noise must be 0 here", "the encoder's own data"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_refused_in_one_line_before_any_work(capsys, tmp_path, case):
    from tests.test_bad_inputs import check_case

    argv, needles = BAD[case]
    check_case(capsys, tmp_path, ["run", "--task", "imitate-swingup", "--preset", "smoke", "--no-progress", *argv],
               *needles)
    assert not (tmp_path / "home" / "experts").exists()


def test_the_task_is_registered_with_its_presets():
    for name in ("imitate-swingup", "imitate-cheetah"):
        spec = registry.get("tasks", name).spec
        assert spec.default_preset == "quick" and {"smoke", "quick", "paper"} <= set(spec.presets)
        _, config = resolve_config(registry.get("encoders", "true-state").spec, spec, "quick")
        assert config["task"]["bc"]["demonstrations"] <= config["task"]["demos"]["episodes"]
