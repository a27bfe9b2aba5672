"""End to end through the installed console script, on the smoke preset."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from mftcn_bench.results.store import ResultStore

pytestmark = pytest.mark.slow


def cli(*args, home, check=True):
    env = {**os.environ, "MFTCN_BENCH_HOME": str(home)}
    proc = subprocess.run([sys.executable, "-m", "mftcn_bench.cli", *args], capture_output=True, text=True,
                          env=env, timeout=600)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}: {proc.stderr[-2000:]}")
    return proc


@pytest.fixture(scope="module")
def smoke_home(tmp_path_factory):
    home = tmp_path_factory.mktemp("home")
    cli("run", "--encoder", "mftcn2", "--task", "cartpole-probe", "--preset", "smoke", "--no-progress",
        home=home)
    return home


def test_smoke_run_prints_table_and_stores_everything(smoke_home):
    store = ResultStore(smoke_home / "results.sqlite")
    (record,) = store.query(task="cartpole-probe", encoder="mftcn2")
    assert record.preset == "smoke" and record.seed == 0
    assert set(record.metrics) >= {"average", "position", "motion", "mse_theta_dot"}
    assert record.versions["torch"] and record.versions["mujoco"] == "3.17.0"
    assert record.config["encoder"]["frames"] == 2 and record.config["task"]["dataset"]["episode_length"] == 100
    assert record.config["encoder_info"]["parameter_count"] > 0
    assert json.loads((smoke_home / "runs" / record.run_id / "result.json").read_text())["run_id"] == record.run_id


def test_second_run_reuses_result_and_new_encoder_reuses_dataset(smoke_home):
    again = cli("run", "--encoder", "mftcn2", "--preset", "smoke", "--no-progress", home=smoke_home)
    assert "reused stored result" in again.stdout and "| Average" in again.stdout
    datasets = list((smoke_home / "datasets").iterdir())
    other = cli("run", "--encoder", "mftcn2", "--preset", "smoke", "--no-progress",
                "--set", "encoder.embedding_dim=8", home=smoke_home)
    assert "finished in" in other.stdout
    assert list((smoke_home / "datasets").iterdir()) == datasets
    runs = ResultStore(smoke_home / "results.sqlite").query(encoder="mftcn2")
    assert sorted(r.config["encoder"]["embedding_dim"] for r in runs) == [8, 32]


def test_report_probe_shows_ours_beside_paper(smoke_home):
    out = cli("report", "probe", "--preset", "smoke", home=smoke_home).stdout
    assert "| smoke" in out and "(0.0401)" in out and "(0.1062)" in out
    default = cli("report", "probe", home=smoke_home).stdout  # the paper and quick presets' runs only
    assert "| smoke" not in default and "(0.0401)" in default
    assert "of preset smoke (`report probe --preset smoke` shows them)" in default


def test_list_shows_descriptions(tmp_path):
    out = cli("list", "encoders", home=tmp_path).stdout
    assert "mftcn5" in out and "lookback 5" in out


BAD_INPUTS = [
    (("run", "--encoder", "mftcn3"), "unknown encoder 'mftcn3'; did you mean"),
    (("run", "--task", "cartpole-prob"), "unknown task 'cartpole-prob'; did you mean cartpole-probe"),
    (("run", "--preset", "smok"), "did you mean smoke"),
    (("run", "--set", "encoder.embeding_dim=8"), "did you mean encoder.embedding_dim"),
    (("run", "--set", "encoder.embedding_dim=eight"), "expected a int"),
    (("run", "--set", "task.dataset.cameras=[\"fixed\", \"top\"]"), "camera 'top' does not exist in cartpole"),
    (("run", "--seed", "-1"), "--seed must be a non-negative integer"),
    (("run", "--set", "encoder.embedding_dim"), "is not KEY=VALUE"),
    (("list", "encoder"), "invalid choice"),
    (("run", "--set", "task.probe.camera=top"), "probe camera 'top' is not one of the dataset's cameras"),
]


@pytest.mark.parametrize("args,message", BAD_INPUTS)
def test_bad_input_is_one_line_exit_2_nothing_written(tmp_path, args, message):
    home = tmp_path / "home"
    proc = cli(*args, home=home, check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in proc.stderr
    assert not (home / "results.sqlite").exists() or not ResultStore(home / "results.sqlite").query()


def test_read_only_home_is_refused(tmp_path):
    home = tmp_path / "ro"
    home.mkdir()
    home.chmod(0o500)
    try:
        if os.access(home, os.W_OK):
            pytest.skip("running as a user that can write anywhere")
        proc = cli("run", home=home, check=False)
        assert proc.returncode == 2 and "not writable" in proc.stderr
    finally:
        home.chmod(0o700)


def test_every_registered_encoder_runs_the_smoke_probe(smoke_home, monkeypatch):
    """Each encoder in the registry, in-process, on the already collected smoke dataset."""
    from mftcn_bench.core import registry
    from mftcn_bench.core.errors import BenchError
    from mftcn_bench.core.home import BenchHome
    from mftcn_bench.run.plan import RunRequest
    from mftcn_bench.run.runner import run

    home = BenchHome.resolve(smoke_home)
    for name in registry.entries("encoders"):
        if name == "inception":  # needs ImageNet weights on disk: the run stops with where to put them
            with pytest.raises(BenchError, match="encoder.model.base.weights"):
                run(RunRequest(name, "cartpole-probe", "smoke"), home, show_progress=False)
            continue
        # pve's 64 triplets a step are most of this test's time at the smoke preset; 16 still train it
        overrides = (("encoder.train.batch_size", 16),) if name == "pve" else ()
        outcome = run(RunRequest(name, "cartpole-probe", "smoke", overrides=overrides), home, show_progress=False)
        assert np.isfinite(outcome.record.metrics["average"]), name
        assert outcome.record.config["encoder_info"]["name"] == name
    assert len(list((smoke_home / "datasets").glob("cartpole-random-*"))) == 1
