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
    # The suite's reward is in [0, 1] per physics step, so a return over a whole episode (the action
    # repeat's rewards summed) lies in [0, episode_length]; a sum over too many steps or repeats breaks it.
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


def _test_returns_by_hand(task: str, record, run_dir) -> list[float]:
    """The returns of the record's test episodes, recomputed without `evaluate_policy`: the trained networks
    from the run's last checkpoint, a fresh environment seeded as the test's (the run seed + EVAL_SEED_OFFSET,
    apart from training's), the action set to tanh(loc) by hand (the TanhNormal's mean action), the rewards
    summed over `agent_steps` steps, each episode ending by its time limit at the last step."""
    from torchrl.envs import ExplorationType, set_exploration_type
    from torchrl.envs.utils import step_mdp

    from mftcn_bench.rl.ppo import EVAL_SEED_OFFSET, PolicyNetworks
    from mftcn_bench.run.runner import RunRequest, prepare

    prepared = prepare(RunRequest("true-state", task, record.preset, record.seed))
    control, encoder = prepared.task, prepared.untrained[0]  # true-state fits nothing
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
