"""End-to-end smoke runs of the control tasks through the CLI: every task with the four reference rows."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from mftcn_bench.cli import main
from mftcn_bench.orchestration.queue import PPO_FRAMES_METRIC, PPO_WALL_METRIC
from mftcn_bench.results.store import ResultStore

ENCODERS = ["true-state", "random-state", "pixels-cnn", "mftcn5"]


@pytest.fixture(scope="module")
def control_home(tmp_path_factory):
    return tmp_path_factory.mktemp("control-home")


@pytest.mark.slow
@pytest.mark.parametrize("task", ["swingup", "swingup-physics-rate", "swingup-moving", "cheetah"])
@pytest.mark.parametrize("encoder", ENCODERS)
def test_smoke_run_stores_returns_and_a_learning_curve(control_home, task, encoder, capsys):
    code = main(["run", "--encoder", encoder, "--task", task, "--preset", "smoke", "--no-progress",
                 "--home", str(control_home)])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "return (mean)" in out
    [record] = ResultStore(control_home / "results.sqlite").query(task=task, encoder=encoder)
    metrics, env, ppo = record.metrics, record.config["task"]["env"], record.config["task"]["ppo"]
    # What the spec implies: a batch is num_envs x episodes_per_batch whole episodes, counted in physics
    # frames; training runs whole batches until `frames`; the test has `eval_episodes` episodes.
    batch_frames = ppo["num_envs"] * ppo["episodes_per_batch"] * env["episode_length"]
    batches = math.ceil(ppo["frames"] / batch_frames)
    assert metrics["episodes"] == ppo["eval_episodes"] and metrics[PPO_FRAMES_METRIC] == batches * batch_frames
    assert 0 < metrics[PPO_WALL_METRIC] <= record.timings["total_s"]  # the clock `sweep status` counts a resumed run by
    test_returns = np.asarray(record.curves["test"]["return"])  # every test episode's return is kept
    assert len(test_returns) == ppo["eval_episodes"] and metrics["return_mean"] == pytest.approx(test_returns.mean())
    assert metrics["return_std"] == pytest.approx(test_returns.std(ddof=1))
    # A cheap sanity bound only (the suite's reward is in [0, 1] per physics step); the exact value of a test
    # episode's return is pinned against dm_control's own stepping by the fast test below
    # (test_test_returns_are_dm_controls_own_rewards_summed_over_the_action_repeat).
    curve = record.curves["train"]
    assert all(0.0 <= r <= env["episode_length"] for r in [*test_returns, *curve["return"]])
    assert curve["frames"] == [float(batch_frames * (k + 1)) for k in range(batches)]  # one point per batch
    assert len(curve["wall_s"]) == batches and sorted(curve["wall_s"]) == curve["wall_s"]
    if encoder == "mftcn5" and task == "swingup":  # the fit's held-out n-pairs loss curve, from the encoder's folder
        assert record.curves["fit"]["step"][-1] == record.config["fit"]["steps"]
        assert record.curves["fit"]["heldout_loss"][-1] == record.config["fit"]["heldout_loss"]
    diagnostics = record.curves["ppo"]  # cleanrl's per-batch diagnostics beside the learning curve
    assert diagnostics["frames"] == curve["frames"]
    assert {"approx_kl", "clip_fraction", "explained_variance"} <= set(diagnostics)
    assert all(len(column) == batches for column in diagnostics.values())
    run_dir = control_home / "runs" / record.run_id
    if encoder == "true-state":  # the test episodes again, stepped here with the stored policy's mean action
        assert test_returns.tolist() == pytest.approx(_test_returns_by_hand(task, record, run_dir), rel=1e-5)
    assert (run_dir / "curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((run_dir / "result.json").read_text())["curves"] == record.curves
    if task == "cheetah":  # one expert serves every row's demonstrations; a row that fits nothing collects
        # none (`tasks.base.OnlineTask`), so the expert is there once mftcn5, whose encoder fits on them, has run
        experts = list((control_home / "experts").glob("cheetah-run-*/expert.pt"))
        assert len(experts) == 1 if encoder == "mftcn5" else len(experts) <= 1


class FixedPolicy:
    """A deterministic stand-in for `PolicyNetworks`: `policy` writes an action that depends on the observation
    (a fixed nonlinear feedback on the true state) and records every action it gives, and the suite instances'
    physics state at each episode's first step (read from the environment `make_env` built)."""

    def __init__(self, agent_steps: int) -> None:
        from tensordict.nn import TensorDictModule

        self.agent_steps, self.calls, self.env = agent_steps, 0, None
        self.actions: list[torch.Tensor] = []
        self.starts: list[list[np.ndarray]] = []
        self.policy = TensorDictModule(self._act, in_keys=["observation"], out_keys=["action"])

    def _act(self, observation: torch.Tensor) -> torch.Tensor:
        from mftcn_bench.rl.suite_env import suite_env_of

        if self.calls % self.agent_steps == 0:  # an episode's first decision: right after the reset
            self.starts.append([e.physics.get_state().copy() for e in suite_env_of(self.env)._envs])
        self.calls += 1
        # true-state cartpole observation: (x_cart, sin theta, cos theta, x_dot, theta_dot)
        x, sin, cos, x_dot, theta_dot = observation.unbind(-1)
        action = torch.tanh(1.5 * sin - 0.7 * cos + 0.2 * theta_dot - 0.5 * x - 0.1 * x_dot).unsqueeze(-1)
        self.actions.append(action.clone())
        return action


def test_test_returns_are_dm_controls_own_rewards_summed_over_the_action_repeat():
    """A test episode's return (`evaluate_policy` on the swingup task's environments, smoke preset) equals the
    sum, over every physics step of the episode, of the reward of dm_control's own `suite.load("cartpole",
    "swingup")` environment stepped with `Environment.step` from the same initial physics state with the same
    actions, each held for the spec's action repeat (8) over the spec's episode length (80 physics steps).
    Pins the action repeat, the episode length, the reward sum and the order of the returned episodes (two
    rounds of two environments): a reward of the repeat lost, an agent step left out of the sum, a scaled
    action or another task's reward all change the figures."""
    from dm_control import suite

    from mftcn_bench.core import registry
    from mftcn_bench.core.specs import resolve_config
    from mftcn_bench.rl.ppo import evaluate_policy
    from mftcn_bench.tasks.control import ControlTask

    encoder_entry, task_entry = registry.get("encoders", "true-state"), registry.get("tasks", "swingup")
    _, config = resolve_config(encoder_entry.spec, task_entry.spec, "smoke")
    task = ControlTask(config["task"], seed=3)
    # What the spec file says, written here so that the replay below does not read the harness's config.
    repeat, physics_steps, agent_steps = 8, 80, 10
    assert (task.env_config.action_repeat, task.env_config.episode_length) == (repeat, physics_steps)
    encoder = encoder_entry.load()(encoder_entry.spec, image_shape=(48, 96), seed=3)
    make_env, _ = task.env_factory(encoder)
    fixed = FixedPolicy(agent_steps)

    def recording_make_env(num_envs: int, seed: int):
        fixed.env = make_env(num_envs, seed)
        return fixed.env

    num_envs, episodes = 2, 4
    returns = evaluate_policy(recording_make_env, fixed, episodes, num_envs, seed=3)
    assert returns.shape == (episodes,) and len(fixed.starts) == episodes // num_envs
    assert len(fixed.actions) == agent_steps * episodes // num_envs
    expected = []
    for round_ in range(episodes // num_envs):  # the returns come round by round, environment by environment
        for i in range(num_envs):
            plain = suite.load("cartpole", "swingup")
            plain.reset()
            with plain.physics.reset_context():
                plain.physics.set_state(fixed.starts[round_][i])
            total = 0.0
            for t in range(agent_steps):
                action = fixed.actions[round_ * agent_steps + t][i].numpy().astype(np.float64)
                for _ in range(repeat):
                    step = plain.step(action)
                    total += step.reward
            expected.append(total)
    assert returns.tolist() == pytest.approx(expected, rel=1e-5), (  # float32 rewards summed: ~1e-7
        f"evaluate_policy returns {returns.tolist()}, dm_control's own stepping {expected}")
    # The figures are informative: the episodes differ, and no return sits at a bound of [0, 80].
    assert len(set(np.round(expected, 3))) == episodes and all(1.0 < r < physics_steps - 1.0 for r in expected)


def _test_returns_by_hand(task: str, record, run_dir) -> list[float]:
    """The returns of the record's test episodes, recomputed without `evaluate_policy`: the trained networks
    from the run's last checkpoint, a fresh environment seeded as the test's (the run seed + EVAL_SEED_OFFSET,
    apart from training's), the action set to tanh(loc) by hand (the TanhNormal's mean action), the rewards
    summed over `agent_steps` steps, each episode ending by its time limit at the last step."""
    from torchrl.envs import ExplorationType, set_exploration_type
    from torchrl.envs.utils import step_mdp

    from mftcn_bench.rl.ppo import EVAL_SEED_OFFSET, PolicyNetworks
    from mftcn_bench.run.plan import RunRequest, prepare_with_encoder

    prepared, encoder = prepare_with_encoder(RunRequest("true-state", task, record.preset, record.seed))
    control = prepared.task  # true-state fits nothing
    make_env, _ = control.env_factory(encoder)
    ppo, steps = control.ppo, control.env_config.agent_steps
    n = min(ppo.num_envs, ppo.eval_episodes)
    env = make_env(n, record.seed + EVAL_SEED_OFFSET)
    nets = PolicyNetworks(env, ppo, None)
    nets.load_state_dict(torch.load(run_dir / "ppo_checkpoint.pt", weights_only=True)["nets"])
    returns: list[float] = []
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            while len(returns) < ppo.eval_episodes:
                td, total = env.reset(), torch.zeros(n, dtype=torch.float64)
                for t in range(steps):
                    td = nets.policy(td)
                    td.set("action", torch.tanh(td.get("loc")))  # the drawn action replaced by the mean
                    td = env.step(td)
                    total += td.get(("next", "reward")).reshape(n).double()
                    assert bool(td.get(("next", "truncated")).all()) == (t == steps - 1)
                    td = step_mdp(td)
                returns.extend(total.tolist())
    finally:
        env.close()
    return returns[:ppo.eval_episodes]


@pytest.mark.slow
@pytest.mark.parametrize("task", ["swingup-difference", "swingup-physics-rate-difference", "swingup-probe-state",
                                  "cheetah-difference"])
def test_smoke_run_of_a_ppo_limit_analysis(control_home, task, capsys):
    """The PPO-limit variants run mftcn5 end to end; the probe-state one stores its readout's test R^2."""
    code = main(["run", "--encoder", "mftcn5", "--task", task, "--preset", "smoke", "--no-progress",
                 "--home", str(control_home)])
    out = capsys.readouterr().out
    assert code == 0, out
    [record] = ResultStore(control_home / "results.sqlite").query(task=task, encoder="mftcn5")
    assert record.metrics["frames"] == 320 and record.config["task"]["env"]["embedding_difference"] is True
    if task == "swingup-probe-state":
        r2 = [record.metrics[f"probe_r2_{k}"] for k in ("x_cart", "sin_theta", "cos_theta", "x_dot", "theta_dot")]
        assert record.metrics["probe_r2_mean"] == pytest.approx(np.mean(r2))
        assert all(np.isfinite(r2)) and "probe R^2 (mean of 5)" in out
        assert any(note.startswith("policy input: the probe's prediction") for note in record.config["notes"])


def _cli(args: list[str], home) -> subprocess.CompletedProcess:
    """The installed command as a new user runs it: a fresh process, MUJOCO_GL unset, one thread."""
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"} | {"OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "mftcn_bench.cli", *args, "--no-progress", "--home", str(home)],
                          capture_output=True, text=True, env=env, timeout=600)


@pytest.mark.slow
def test_an_agent_rate_probe_run_then_a_swingup_run_share_one_dataset_and_one_fit_and_print_no_glfw_line(tmp_path):
    """With MUJOCO_GL unset (a new user's shell), the probe and the control path choose the same GL backend
    before MuJoCo is first imported: no GLFW warning, one data set, one fit of the shared encoder."""
    probe = _cli(["run", "--encoder", "mftcn1", "--task", "cartpole-probe-agent-rate", "--preset", "smoke"], tmp_path)
    control = _cli(["run", "--encoder", "mftcn1", "--task", "swingup", "--preset", "smoke"], tmp_path)
    assert probe.returncode == 0 and control.returncode == 0, probe.stderr + control.stderr
    assert "GLFW" not in probe.stderr + control.stderr
    assert len([p for p in (tmp_path / "datasets").iterdir() if not p.name.startswith(".")]) == 1
    assert len([p for p in (tmp_path / "encoders").iterdir() if not p.name.startswith(".")]) == 1
    [record] = ResultStore(tmp_path / "results.sqlite").query(task="swingup")
    assert record.config["fit"]["reused"] is True and record.config["fit"]["fitted"] is False


def test_no_progress_reaches_ppos_progress_bar(tmp_path, monkeypatch):
    """`--no-progress` turns PPO's bar off (the runner tells the task, `tasks.base.ShowsProgress`); without
    it tqdm decides (a bar on a terminal)."""
    import tqdm

    disabled: list[object] = []
    real = tqdm.tqdm

    def recording(*args, **kwargs):
        if str(kwargs.get("desc", "")).startswith("ppo "):
            disabled.append(kwargs.get("disable"))
        return real(*args, **kwargs)

    monkeypatch.setattr(tqdm, "tqdm", recording)
    for flag in (["--no-progress"], []):
        assert main(["run", "--encoder", "true-state", "--task", "swingup", "--preset", "smoke", "--force",
                     "--home", str(tmp_path), *flag]) == 0
    assert disabled == [True, None]
