"""End-to-end smoke runs of the control tasks through the CLI: every task with the four reference rows."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from mftcn_bench.cli import main
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
    metrics = record.metrics
    assert metrics["episodes"] == 2 and metrics["frames"] == 320
    test_returns = np.asarray(record.curves["test"]["return"])  # every test episode's return is kept
    assert len(test_returns) == 2 and metrics["return_mean"] == pytest.approx(test_returns.mean())
    assert metrics["return_std"] == pytest.approx(test_returns.std(ddof=1))
    assert all(0.0 <= r <= 80.0 for r in test_returns)  # smoke episodes of <= 80 steps, reward <= 1 a step
    curve = record.curves["train"]
    assert curve["frames"][-1] == 320.0 and sorted(curve["frames"]) == curve["frames"]
    assert len(curve["return"]) == len(curve["wall_s"]) == len(curve["frames"]) >= 2
    run_dir = control_home / "runs" / record.run_id
    assert (run_dir / "curve.png").stat().st_size > 0
    assert json.loads((run_dir / "result.json").read_text())["curves"] == record.curves
    if task == "cheetah":  # one expert serves every row's demonstrations
        assert len(list((control_home / "experts").glob("cheetah-run-*/expert.pt"))) == 1


@pytest.mark.slow
@pytest.mark.parametrize("task", ["swingup-difference", "swingup-physics-rate-difference", "swingup-probe-state"])
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
