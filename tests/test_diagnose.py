"""`mftcn-bench diagnose coverage|probe|policy` (`mftcn_bench.diagnose`) give the right numbers, and the one-off
experiments kept in scripts/diagnostics still run."""

import importlib.util
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mftcn_bench.cli import main
from mftcn_bench.core.home import BenchHome
from mftcn_bench.data.dataset import MultiViewDataset, ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config
from mftcn_bench.diagnose.coverage import cartpole_physics, coverage, dataset_coverage, dataset_states
from mftcn_bench.diagnose.policy_range import render_states, replay_policy
from mftcn_bench.diagnose.state_probe import probe_cameras
from mftcn_bench.run.plan import RunRequest, prepare

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts" / "diagnostics"
PROBE_TASK = "cartpole-probe-agent-rate"  # its smoke data set is swing-up's: one collection for the module


def load(name):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def smoke_home(tmp_path_factory):
    """One results home with the smoke preset's cartpole agent-rate data set (6 train and 2 test episodes of
    100 frames, cameras fixed and lookatcart at 96x48), collected once for this file."""
    root = tmp_path_factory.mktemp("home")
    assert main(["data", "collect", PROBE_TASK, "--preset", "smoke", "--no-progress", "--home", str(root)]) == 0
    return root


def smoke_dataset(home: Path) -> MultiViewDataset:
    [folder] = (home / "datasets").glob("cartpole-agent-rate-*")
    return MultiViewDataset(folder)


# -- coverage ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("height", "width"), [(160, 160), (48, 96)])
def test_camera_coverage_agrees_with_the_segmentation_render(height, width):
    physics = cartpole_physics()
    # x in m, theta in rad: in the middle, near and past the square image's edge (the cart is cut beyond
    # |x| = 1.40 at 160x160), the pole along the rail towards the edge and upright
    states = np.array([[0.0, 0.0], [1.0, 0.0], [1.5, 0.0], [-1.8, 0.0], [1.0, np.pi / 2], [-0.3, -np.pi / 2]])
    seen = coverage(physics, "fixed", height, width, states)
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


@pytest.mark.parametrize(("height", "width"), [(160, 160), (48, 96)])
def test_the_view_edge_is_where_the_fixed_cameras_fovy_puts_it(height, width):
    physics = cartpole_physics()
    fixed = physics.model.name2id("fixed", "camera")
    assert physics.data.cam_xpos[fixed].tolist() == [0.0, -4.0, 1.0] and physics.model.cam_fovy[fixed] == 45.0
    # By hand: the suite's `fixed` camera sits at y = -4 looking along +y with fovy 45 degrees; the cart's
    # centre is at y = 0, 4 m away, so the image spans 4 tan(22.5 deg) = 1.657 m either side vertically and
    # that times width / height horizontally (1.657 m at 160x160, 3.314 m at 96x48).
    half_width = 4.0 * math.tan(math.radians(45.0) / 2) * width / height
    assert half_width == pytest.approx(1.657 if width == height else 3.314, abs=1e-3)
    states = np.array([[0.0, 0.0], [0.99 * half_width, 0.0], [1.01 * half_width, 0.0], [-1.01 * half_width, np.pi],
                       [half_width + 1.0, 0.0]])
    seen = coverage(physics, "fixed", height, width, states)
    # x = 0: the whole cart, its centre and the upright pole's tip in view
    assert not seen.cart_cut[0] and not seen.cart_centre_out[0] and not seen.tip_out[0]
    # just inside the edge the centre is seen and the cart (0.2 m either side of it) cut; just past it, either side,
    # the centre is out
    assert seen.cart_centre_out.tolist() == [False, False, True, True, True]
    assert seen.cart_cut.tolist() == [False, True, True, True, True]
    assert seen.tip_out[4]


def test_dataset_coverage_counts_every_frame_of_a_smoke_data_set(smoke_home):
    dataset = smoke_dataset(smoke_home)
    found = dataset_coverage(dataset)
    states = np.concatenate([dataset.load(i).state for s in ("train", "test") for i in dataset.episodes(s)])
    assert found.frames == len(states) == 800 and (found.height, found.width) == (48, 96)
    assert np.array_equal(np.sort(dataset_states(dataset), axis=0), np.sort(states, axis=0))
    distance = np.abs(states[:, 0])
    assert (found.cart.median, found.cart.p90, found.cart.max) == pytest.approx(
        (np.median(distance), np.quantile(distance, 0.9), distance.max()))
    assert [c.camera for c in found.cameras] == ["fixed", "lookatcart"]
    # the whole rail (+-1.8 m and the cart's 0.2 m either side) lies inside the fixed view's +-3.31 m at 96x48
    fixed = found.cameras[0]
    assert (fixed.cart_cut, fixed.cart_centre_out, fixed.tip_out) == (0.0, 0.0, 0.0)
    tips = coverage(cartpole_physics(), "lookatcart", 48, 96, states).tip_out
    assert found.cameras[1].tip_out == pytest.approx(tips.mean())
    assert [c.camera for c in dataset_coverage(dataset, ["lookatcart"]).cameras] == ["lookatcart"]


def test_coverage_command_prints_the_fractions(smoke_home, capsys):
    folder = smoke_dataset(smoke_home).root
    assert main(["diagnose", "coverage", str(folder), "--cameras", "fixed"]) == 0
    out = capsys.readouterr().out
    assert re.search(r": 800 frames at 96x48; \|x\| median [\d.]+, 90th percentile [\d.]+, max [\d.]+", out), out
    assert re.search(r"\| fixed +\| 0\.0000 +\| 0\.0000 +\| 0\.0000 +\|", out), out


@pytest.mark.parametrize(("make", "message"), [
    (lambda tmp: tmp, "is not a collected dataset (no manifest.json)"),
    (lambda tmp: ensure_dataset(tmp, synthetic_config(height=48, width=96), synthetic_collector,
                                show_progress=False).root, "diagnose coverage reads cartpole data sets"),
])
def test_coverage_of_a_folder_that_is_no_cartpole_data_set_is_one_line_exit_2(tmp_path, capsys, make, message):
    assert main(["diagnose", "coverage", str(make(tmp_path))]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_an_unknown_camera_is_one_line_exit_2(smoke_home, capsys):
    assert main(["diagnose", "coverage", str(smoke_dataset(smoke_home).root), "--cameras", "fixd"]) == 2
    err = capsys.readouterr().err
    assert "unknown camera 'fixd'; did you mean fixed?" in err and err.count("\n") == 1, err


# -- state probe ------------------------------------------------------------------------------------------

def test_the_probe_reads_the_true_state_from_true_state(smoke_home):
    found = probe_cameras(RunRequest("true-state", PROBE_TASK, "smoke"), BenchHome.resolve(smoke_home), ["fixed"])
    assert found.dimensions == ("x_cart", "sin_theta", "cos_theta", "x_dot", "theta_dot")
    [fixed] = found.cameras
    # 6 train and 2 test episodes of 100 frames; the state itself as the features: every dimension near 1
    assert (fixed.camera, fixed.train_frames, fixed.test.frames, fixed.random_actions) == ("fixed", 600, 200, None)
    assert min(fixed.test.r2) > 0.95, fixed.test


def test_the_probe_reads_nothing_from_random_state_on_any_camera(smoke_home, capsys):
    assert main(["diagnose", "probe", "--encoder", "random-state", "--task", PROBE_TASK, "--preset", "smoke",
                 "--no-progress", "--home", str(smoke_home)]) == 0
    out = capsys.readouterr().out
    assert "fitted on 600 train frames; R^2 on 200 test frames" in out, out
    header = next(line for line in out.splitlines() if line.startswith("| R^2"))
    assert [c.strip() for c in header.strip("|").split("|")] == ["R^2", "fixed: test", "lookatcart: test"]
    rows = {cells[0]: [float(c) for c in cells[1:]] for cells in
            ([c.strip() for c in line.strip("|").split("|")] for line in out.splitlines()
             if line.startswith("| ") and not line.startswith("| R^2"))}
    assert list(rows) == ["x_cart", "sin_theta", "cos_theta", "x_dot", "theta_dot", "mean"]
    # noise: no dimension explained on the held-out episodes (R^2 near 0, or below: a fit to noise)
    assert all(value < 0.1 for values in rows.values() for value in values), out
    assert all(value < 0.05 for value in rows["mean"]), out


def test_the_probe_on_random_action_episodes_of_demonstrations(tmp_path):
    found = probe_cameras(RunRequest("true-state", "cheetah", "smoke"), BenchHome.resolve(tmp_path), ["side"], 1)
    [side] = found.cameras
    assert found.random_episodes == 1 and len(found.dimensions) == 17
    # cheetah smoke: 3 train and 1 test demonstration of 100 frames, one random-action episode of 100 frames
    assert (side.train_frames, side.test.frames, side.random_actions.frames) == (300, 100, 100)
    assert side.test.mean > 0.5, side.test  # true state on held-out demonstrations
    assert all(math.isfinite(v) for v in side.random_actions.r2)


@pytest.mark.parametrize(("args", "message"), [
    (["--random-episodes", "-1"], "--random-episodes must be >= 0, got -1"),
    (["--random-episodes", "1"], "needs a task whose dataset is an expert's demonstrations"),
    (["--cameras", "top"], "unknown camera 'top'"),
    (["--random-episodes", "two"], "expected a whole number, got 'two'"),
])
def test_bad_probe_requests_are_one_line_exit_2_before_any_work(tmp_path, capsys, args, message):
    assert main(["diagnose", "probe", "--encoder", "true-state", "--task", "swingup", "--preset", "smoke",
                 *args, "--home", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "datasets").exists() or not any((tmp_path / "datasets").iterdir())


def test_an_unknown_encoder_is_one_line_exit_2(tmp_path, capsys):
    assert main(["diagnose", "probe", "--encoder", "true-stat", "--task", "swingup", "--home", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "unknown encoder 'true-stat'" in err and err.count("\n") == 1, err



# -- policy -----------------------------------------------------------------------------------------------

def test_the_policys_frames_are_drawn_as_its_environment_draws_them(smoke_home):
    dataset = smoke_dataset(smoke_home)
    episode = dataset.load(dataset.episodes("test")[0])
    config = prepare(RunRequest("true-state", "swingup", "smoke")).task.env_config
    [frames] = render_states(config, [episode.state[:12]])
    # the data set's fixed view at the same states, pixel for pixel
    assert np.array_equal(frames, episode.frames[dataset.cameras.index("fixed")][:12])


def test_a_policy_without_its_run_is_one_line_exit_2(tmp_path, capsys):
    assert main(["diagnose", "policy", "--encoder", "true-state", "--task", "swingup", "--preset", "smoke",
                 "--home", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "its run folder" in err and "is missing or unfinished (no result.json); run `mftcn-bench run --encoder " \
                                      "true-state --task swingup --preset smoke --seed 0` first" in err, err
    assert err.count("\n") == 1, err


@pytest.mark.parametrize(("args", "message"), [
    (["--task", "cartpole-probe", "--episodes", "2"], "needs a cartpole control task"),
    (["--task", "cheetah", "--episodes", "2"], "needs a cartpole control task"),
    (["--task", "swingup", "--episodes", "0"], "--episodes must be >= 1, got 0"),
])
def test_bad_policy_requests_are_one_line_exit_2(tmp_path, capsys, args, message):
    assert main(["diagnose", "policy", "--encoder", "true-state", *args, "--home", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


@pytest.mark.slow
def test_policy_replays_the_runs_own_test_episodes(smoke_home, capsys):
    assert main(["run", "--encoder", "true-state", "--task", "swingup", "--preset", "smoke", "--no-progress",
                 "--home", str(smoke_home)]) == 0
    capsys.readouterr()
    found = replay_policy(RunRequest("true-state", "swingup", "smoke"), BenchHome.resolve(smoke_home), 2)
    # 2 episodes of 80 physics steps at action repeat 8: 10 agent steps and the first frame each
    assert found.episodes == 2 and found.frames == 22
    assert found.returns_replayed == found.returns_stored
    rail = float(cartpole_physics().named.model.jnt_range["slider"][1])  # the slider's limit, 1.8 m
    cart = found.cart
    assert all(math.isfinite(v) and 0 <= v <= rail for v in (cart.median, cart.p90, cart.max)), cart
    assert cart.median <= cart.p90 <= cart.max
    # at 96x48 the fixed camera sees the whole rail
    assert (found.camera.camera, found.camera.cart_cut, found.camera.tip_out) == ("fixed", 0.0, 0.0)
    # true state read back from the data set's held-out frames, and on the policy's 22 frames the positions
    # and velocities (cos theta barely varies near the hanging rest, so its R^2 says little)
    assert found.probe_test.frames == 200 and min(found.probe_test.r2) > 0.95, found.probe_test
    assert found.probe.frames == 22 and found.probe.r2[0] > 0.5, found.probe
    assert main(["diagnose", "policy", "--encoder", "true-state", "--task", "swingup", "--preset", "smoke",
                 "--episodes", "2", "--no-progress", "--home", str(smoke_home)]) == 0
    out = capsys.readouterr().out
    assert f"run {found.run_id}: 2 test episodes, 22 frames" in out, out
    replayed = re.search(r"returns replayed: (.*)", out).group(1).split()
    stored = re.search(r"returns stored: +(.*)", out).group(1).split()
    assert len(replayed) == 2 and replayed == stored, out
    assert re.search(r"\| fixed +\| 0\.0000 +\| 0\.0000 +\| 0\.0000 +\|", out), out
    assert re.search(r"\| mean +\| [\d.]+ +\| -?[\d.]+ +\|", out), out


# -- the one-off experiments in scripts/diagnostics -------------------------------------------------------

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
def test_script_runs(tmp_path, command):
    folder = ensure_dataset(tmp_path, synthetic_config(height=48, width=96), synthetic_collector,
                            show_progress=False).root
    done = subprocess.run([sys.executable, str(SCRIPTS / command[0]), str(folder), *command[1:], "--steps", "3"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "step 3:" in done.stdout
