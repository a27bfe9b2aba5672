"""Sweeps: grid parsing, validation before any work, a tiny sweep through the local pool and through a
local Ray instance (identical metrics for the same seeds), and a rerun that redoes nothing."""

import os

import pytest

from mftcn_bench.cli import main
from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.home import BenchHome
from mftcn_bench.orchestration.sweep import SweepRequest, parse_seeds, run_sweep
from mftcn_bench.results.store import ResultStore
from tests.plugins import install

# Rendering costs ~3 ms a frame: 3 episodes of 30 frames x 2 views; encoders without training.
TINY = ("task.dataset.train_episodes=2", "task.dataset.test_episodes=1", "task.dataset.episode_length=30",
        "task.probe.batch_size=16")
ENCODERS = ("true-state", "random-state")
SEEDS = (0, 1)


def tiny_overrides():
    from mftcn_bench.core.specs import parse_override

    return tuple(parse_override(o) for o in TINY)


def sweep_args(encoders, *extra):
    args = ["sweep", "--encoders", ",".join(encoders), "--tasks", "cartpole-probe", "--seeds", "0-1",
            "--preset", "smoke", "--workers", "2", *extra]
    for override in TINY:
        args += ["--set", override]
    return args


def metrics_by_job(home):
    return {(r.encoder, r.seed): r.metrics for r in ResultStore(home.database).query()}


class NoWork:
    """An executor for a sweep that must find everything done."""

    name = "none"

    def map(self, specs):
        assert not specs, f"a rerun submitted {len(specs)} jobs"
        return iter(())

    def close(self):
        pass


def test_parse_seeds():
    assert parse_seeds("0-4") == (0, 1, 2, 3, 4)
    assert parse_seeds("0,2,5") == (0, 2, 5)
    assert parse_seeds("0-2,7,1") == (0, 1, 2, 7)
    for bad in ("a", "3-1", "-1", "0-", ""):
        with pytest.raises(SpecError, match="--seeds"):
            parse_seeds(bad)


@pytest.mark.parametrize("args, message", [
    (["--encoders", "true-state,tru-state"], "unknown encoder 'tru-state'"),
    (["--encoders", "true-state", "--preset", "smok"], "did you mean smoke"),
    (["--encoders", "true-state", "--set", "task.probe.epoch=3"], "did you mean task.probe.epochs"),
    (["--encoders", "true-state", "--workers", "0"], "--workers must be >= 1"),
    (["--encoders", "true-state", "--address", "ray://127.0.0.1:1"], "--address is for --executor ray"),
])
def test_bad_input_is_one_line_exit_2_before_any_work(tmp_path, monkeypatch, capsys, args, message):
    monkeypatch.setenv("MFTCN_BENCH_HOME", str(tmp_path / "home"))
    assert main(["sweep", "--tasks", "cartpole-probe", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "home" / "datasets").exists()


FAILING = """
from mftcn_bench.core.errors import TrainingError
from mftcn_bench.encoders.baselines import TrueStateEncoder


class FailingFit(TrueStateEncoder):
    needs_fit = True

    def fit(self, dataset, budget, progress, workdir):
        raise TrainingError("deliberate failure of this encoder's fit")
"""


@pytest.fixture(scope="module")
def local_home(tmp_path_factory):
    """A local-pool sweep (with one encoder whose fit fails, from a plugin), run once."""
    home = BenchHome.resolve(tmp_path_factory.mktemp("local"))
    mp = pytest.MonkeyPatch()
    mp.setenv("MFTCN_BENCH_HOME", str(home.root))
    plugin_root = tmp_path_factory.mktemp("plugin")
    install(mp, plugin_root, "failplug", "1.0", {"enc": FAILING}, {"failing-fit": "enc:FailingFit"})
    mp.setenv("PYTHONPATH", os.pathsep.join([str(plugin_root), os.environ.get("PYTHONPATH", "")]))
    try:
        code = main(sweep_args((*ENCODERS, "failing-fit")))
    finally:
        mp.undo()
    return home, code


@pytest.mark.slow
def test_local_sweep_stores_every_run_and_a_failed_job_only_fails_itself(local_home, capsys):
    home, code = local_home
    assert code == 1  # failing-fit failed: the sweep went on, and says so in its exit code
    assert set(metrics_by_job(home)) == {(e, s) for e in ENCODERS for s in SEEDS}
    for record in ResultStore(home.database).query():
        assert (home.runs / record.run_id / "result.json").exists()


@pytest.mark.slow
def test_rerun_skips_finished_runs(local_home):
    home, _ = local_home
    before = metrics_by_job(home)
    request = SweepRequest(ENCODERS, ("cartpole-probe",), SEEDS, "smoke", tiny_overrides())
    jobs = run_sweep(request, home, echo=lambda line: None, executor=NoWork())
    assert [j.status for j in jobs] == ["reused"] * 4
    assert metrics_by_job(home) == before and len(ResultStore(home.database).query()) == 4


@pytest.mark.slow
def test_ray_sweep_gives_the_same_metrics_as_the_local_pool(local_home, tmp_path):
    ray = pytest.importorskip("ray")
    home, _ = local_home
    ray_home = BenchHome.resolve(tmp_path / "ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        request = SweepRequest(ENCODERS, ("cartpole-probe",), SEEDS, "smoke", tiny_overrides(), executor="ray")
        jobs = run_sweep(request, ray_home, echo=lambda line: None)
    finally:
        ray.shutdown()
    assert [j.status for j in jobs] == ["done"] * 4
    local = {(r.encoder, r.seed): r for r in ResultStore(home.database).query()}
    for record in ResultStore(ray_home.database).query():
        assert record.run_id == local[(record.encoder, record.seed)].run_id
        assert record.metrics == local[(record.encoder, record.seed)].metrics
    assert metrics_by_job(ray_home) == metrics_by_job(home)


class InstantJobs:
    """An executor whose data sets and fits succeed, each said to take 30 s (the first fit reused, taking 0.5 s),
    and whose runs fail, in submission order."""

    name = "instant"

    def map(self, specs):
        from mftcn_bench.orchestration.jobs import JobResult

        for i, spec in enumerate(specs):
            reused = spec.kind == "encoder" and i == 0
            yield i, (JobResult(False, error="not run here") if spec.kind == "run" else
                      JobResult(True, fingerprint="f" * 16, reused=reused, seconds=0.5 if reused else 30.0))

    def close(self):
        pass


class Stages:
    def __init__(self):
        self.seen = []

    def jobs_changed(self, jobs):
        pass

    def stage_changed(self, stage):
        self.seen.append((stage.kind, stage.done, stage.total, stage.worked, stage.worked_s))

    def record_stored(self, record):
        pass


def test_a_sweep_tells_its_listener_each_stage_and_how_many_of_its_jobs_are_done(tmp_path):
    """Data sets, then one fit per (encoder that trains, seed), then the runs: what `sweep status` reads; a
    reused fit is counted done but not in the pace (`worked`, `worked_s`)."""
    from mftcn_bench.orchestration.sweep import Sweep

    listener = Stages()
    request = SweepRequest(("true-state", "mftcn1"), ("cartpole-probe",), SEEDS, "smoke", tiny_overrides())
    Sweep(request, BenchHome.resolve(tmp_path / "home"), echo=lambda line: None, listener=listener).run(InstantJobs())
    assert listener.seen == [("dataset", 0, 1, 0, 0.0), ("dataset", 1, 1, 1, 30.0), ("encoder", 0, 2, 0, 0.0),
                             ("encoder", 1, 2, 0, 0.0), ("encoder", 2, 2, 1, 30.0),
                             *(("run", n, 4, 0, 0.0) for n in range(5))]
