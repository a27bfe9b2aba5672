"""The diagnostic scripts in docs/diagnostics run on a (synthetic) collected dataset."""

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config

DIAGNOSTICS = Path(__file__).resolve().parent.parent / "docs" / "diagnostics"


def load(name):
    spec = importlib.util.spec_from_file_location(name, DIAGNOSTICS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_pick_spread_keeps_the_gap_within_an_episode():
    pick_spread = load("cart_matched_batches").pick_spread
    episode = np.array([0, 0, 0, 0, 1, 1])
    time_step = np.array([0, 3, 8, 20, 0, 2])
    picked = pick_spread(np.arange(6), episode, time_step, count=10, gap=8)
    assert picked.tolist() == [0, 2, 3, 4]  # 1 (3 frames after 0) and 5 (2 after 4) are too close
    assert pick_spread(np.arange(6), episode, time_step, count=2, gap=8).tolist() == [0, 2]


@pytest.mark.parametrize("command", [
    ["cart_matched_batches.py", "--batches", "cart-matched", "--tolerance", "10"],
    ["cart_matched_batches.py", "--batches", "random"],
    ["supervised_pole.py"],
])
def test_diagnostic_runs(tmp_path, command):
    ensure_dataset(tmp_path, synthetic_config(height=48, width=96), synthetic_collector, show_progress=False)
    folder = next(p for p in tmp_path.iterdir() if p.is_dir())
    steps = ["--steps", "3"]
    done = subprocess.run([sys.executable, str(DIAGNOSTICS / command[0]), str(folder), *command[1:], *steps],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "step 3:" in done.stdout


@pytest.fixture(scope="module")
def smoke_home(tmp_path_factory):
    """One results home for the probe tests, so swing-up's smoke dataset is collected once."""
    return tmp_path_factory.mktemp("home")


@pytest.mark.parametrize(("encoder", "low", "high"), [("true-state", 0.6, 1.0), ("random-state", -1.0, 0.2)])
def test_embedding_state_probe_tells_state_from_noise(smoke_home, encoder, low, high):
    done = run_probe(smoke_home, "--encoder", encoder, "--task", "swingup", "--preset", "smoke")
    assert done.returncode == 0, done.stderr
    mean = float(re.search(r"test split: mean R\^2 (-?[\d.]+)", done.stdout).group(1))
    # smoke: 600 train frames, one of its 6 episodes held out for early stopping, so true state is not fitted
    # exactly (0.69 here); noise stays near or below 0
    assert low <= mean <= high, done.stdout


def run_probe(home, *args):
    return subprocess.run([sys.executable, str(DIAGNOSTICS / "embedding_state_probe.py"), *args], capture_output=True,
                          text=True, timeout=600, env={**os.environ, "MFTCN_BENCH_HOME": str(home)})


def test_embedding_state_probe_on_random_action_episodes(tmp_path):
    done = run_probe(tmp_path, "--encoder", "true-state", "--task", "cheetah", "--preset", "smoke",
                     "--random-episodes", "1")
    assert done.returncode == 0, done.stderr
    assert re.search(r"1 random-action episodes \(100 frames\): mean R\^2 -?[\d.]+", done.stdout), done.stdout


def test_random_action_episodes_need_a_task_with_demonstrations(smoke_home):
    done = run_probe(smoke_home, "--encoder", "true-state", "--task", "swingup", "--preset", "smoke",
                     "--random-episodes", "1")
    assert done.returncode != 0
    assert "needs a task whose dataset is an expert's demonstrations" in done.stderr


@pytest.mark.parametrize(("height", "width"), [(160, 160), (48, 96)])
def test_camera_coverage_agrees_with_the_segmentation_render(height, width):
    coverage = load("camera_coverage")
    physics = coverage.cartpole_physics()
    # x in m, theta in rad: in the middle, near and past the square image's edge (the cart is cut beyond
    # |x| = 1.40 at 160x160), the pole along the rail towards the edge and upright
    states = np.array([[0.0, 0.0], [1.0, 0.0], [1.5, 0.0], [-1.8, 0.0], [1.0, np.pi / 2], [-0.3, -np.pi / 2]])
    seen = coverage.coverage(physics, "fixed", height, width, states)
    cart, pole = physics.model.name2id("cart", "geom"), physics.model.name2id("pole_1", "geom")
    for index, (x, theta) in enumerate(states):
        physics.data.qpos[:] = (x, theta)
        physics.forward()
        geoms = physics.render(height, width, camera_id="fixed", segmentation=True)[..., 0]
        edge = np.concatenate([geoms[0], geoms[-1], geoms[:, 0], geoms[:, -1]])
        # cut or out of the image altogether
        assert seen.cart_cut[index] == (cart in edge or cart not in geoms), (x, theta)
        assert seen.tip_out[index] == (pole in edge or pole not in geoms), (x, theta)
    if width == 160:
        assert seen.cart_cut.tolist() == [False, False, True, True, False, False]
        assert seen.tip_out.tolist() == [False, False, False, True, True, False]
    else:
        assert not seen.cart_cut.any() and not seen.tip_out.any()


def test_policy_cart_range_replays_the_runs_own_test_episodes(tmp_path):
    home = {**os.environ, "MFTCN_BENCH_HOME": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", "import sys; from mftcn_bench.cli import main; sys.exit(main())",
                           "run", "--encoder", "true-state", "--task", "swingup", "--preset", "smoke", "--no-progress"],
                          capture_output=True, text=True, timeout=600, env=home)
    assert done.returncode == 0, done.stderr
    done = subprocess.run([sys.executable, str(DIAGNOSTICS / "policy_cart_range.py"), "--encoder", "true-state",
                           "--task", "swingup", "--preset", "smoke", "--episodes", "2"],
                          capture_output=True, text=True, timeout=600, env=home)
    assert done.returncode == 0, done.stderr
    replayed = re.search(r"returns replayed: (.*)", done.stdout).group(1).split()
    stored = re.search(r"returns stored: +(.*)", done.stdout).group(1).split()
    assert len(replayed) == len(stored) == 2 and replayed == stored, done.stdout
    # 2 episodes of 80 physics steps at action repeat 8: 10 agent steps and the first frame each
    assert "2 test episodes, 22 frames" in done.stdout, done.stdout
    assert re.search(r"fixed at 96x48: cart cut by the edge 0\.000", done.stdout), done.stdout
