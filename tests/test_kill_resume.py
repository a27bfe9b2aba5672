"""Kill and resume: a real `mftcn-bench` process is SIGKILLed in the middle of its work, then the same
command is run again. It must complete, reuse what was finished, never read a half-written file, leave
a store that passes SQLite's integrity check, and hold exactly one result.

Also here, because it needs real processes too: four `mftcn-bench run` processes at once on one home.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from mftcn_bench.data.chunks import read_chunk
from mftcn_bench.results.store import ResultStore

pytestmark = pytest.mark.slow

# The smoke preset, smaller: 5 + 1 episodes of 24 frames at 48x24 (two views), a small probe.
EPISODES = 6
SMALL = ["--preset", "smoke", "--no-progress", "--set", "task.dataset.episode_length=24",
         "--set", "task.dataset.train_episodes=5", "--set", "task.dataset.test_episodes=1",
         "--set", "task.dataset.height=24", "--set", "task.dataset.width=48",
         "--set", "task.probe.epochs=5", "--set", "task.probe.batch_size=32", "--set", "task.probe.hidden=[32]"]


def synthetic_dataset(home: Path, args: list[str]) -> None:
    """Make the dataset `mftcn-bench run *args` needs with the synthetic collector (nothing rendered): the
    run finds it (a dataset's id is its config) and goes straight to the encoder."""
    from mftcn_bench.core.specs import parse_override
    from mftcn_bench.data.dataset import ensure_dataset
    from mftcn_bench.data.synthetic import synthetic_collector
    from mftcn_bench.run.plan import RunRequest, prepare

    overrides = tuple(parse_override(args[i + 1]) for i, a in enumerate(args) if a == "--set")
    prepared = prepare(RunRequest(args[args.index("--encoder") + 1], "cartpole-probe", "smoke", 0, overrides))
    ensure_dataset(home / "datasets", prepared.task.dataset_config, synthetic_collector, show_progress=False)


def env_for(home: Path) -> dict[str, str]:
    return {**os.environ, "MFTCN_BENCH_HOME": str(home), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
            "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parent.parent),
                                           os.environ.get("PYTHONPATH", "")])}


def cli(home: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "mftcn_bench.cli", *args], capture_output=True, text=True,
                          env=env_for(home), timeout=timeout)
    assert proc.returncode == 0, f"exit {proc.returncode}: {proc.stderr[-3000:]}"
    return proc


def kill_when(home: Path, args: list[str], ready: Callable[[], bool], timeout: float = 120,
              group: bool = False) -> None:
    """Start `mftcn-bench *args`, SIGKILL it as soon as `ready()` holds (with `group`, it and every process
    it started, as when a machine goes down). Fails if it finished first."""
    proc = subprocess.Popen([sys.executable, "-m", "mftcn_bench.cli", *args], env=env_for(home),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=group)
    deadline = time.monotonic() + timeout
    try:
        while not ready():
            assert proc.poll() is None, f"finished (exit {proc.returncode}) before the kill point: " \
                                        f"{proc.stderr.read().decode()[-2000:]}"
            assert time.monotonic() < deadline, "the kill point was never reached"
            time.sleep(0.02)
        if group:
            os.killpg(proc.pid, signal.SIGKILL)
        else:
            os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL


def one_result(home: Path):
    store = ResultStore(home / "results.sqlite")
    assert store.integrity_ok()
    (record,) = store.query()
    return record


def test_killed_dataset_collection_resumes_from_its_finished_chunks(tmp_path):
    home = tmp_path / "home"
    args = ["run", "--encoder", "random-state", *SMALL]

    def some_chunks_done() -> bool:
        try:
            return any(len(json.loads(p.read_text())) >= 2 for p in home.glob("datasets/*/progress.json"))
        except FileNotFoundError:  # collection just finished: too late, and the kill_when assertion says so
            return False

    kill_when(home, args, some_chunks_done)
    (root,) = home.glob("datasets/cartpole-random-*")
    assert not (root / "manifest.json").exists()
    done = {c["file"]: c["sha256"] for c in json.loads((root / "progress.json").read_text())}
    kept = {name: (root / name).stat().st_mtime_ns for name in done}
    missing = [f"ep{i:05d}.npz" for i in range(EPISODES) if f"ep{i:05d}.npz" not in done]
    assert missing, "killed after the last chunk: no collection left to resume"
    # What a kill can leave besides: a chunk's temporary file, and a chunk written but not yet recorded.
    (root / f".{missing[0]}.tmp-99999").write_bytes(b"half a chunk")
    (root / missing[-1]).write_bytes(b"a chunk the progress file does not list")

    cli(home, *args)
    manifest = json.loads((root / "manifest.json").read_text())
    assert not (root / "progress.json").exists() and not list(root.glob(".*tmp*"))
    assert len(manifest["chunks"]) == EPISODES
    for name, mtime in kept.items():  # finished chunks were reused, not collected again
        assert (root / name).stat().st_mtime_ns == mtime
    for chunk in manifest["chunks"]:  # every chunk is whole and matches its checksum
        read_chunk(root / chunk["file"], chunk["sha256"])
        if chunk["file"] in done:
            assert chunk["sha256"] == done[chunk["file"]]
    record = one_result(home)
    assert record.dataset_id and (home / "runs" / record.run_id / "result.json").exists()


def test_killed_encoder_training_resumes_from_its_checkpoint(tmp_path):
    home = tmp_path / "home"
    args = ["run", "--encoder", "mftcn1", *SMALL, "--set", "encoder.train.steps=60",
            "--set", "encoder.train.checkpoint_every=5", "--set", "encoder.model.adapter_channels=16",
            "--set", "encoder.model.temporal_channels=16", "--set", "encoder.train.batch_timesteps=8"]
    synthetic_dataset(home, args)
    kill_when(home, args, lambda: bool(list(home.glob("encoders/mftcn1-*/train_checkpoint.pt"))))
    (workdir,) = home.glob("encoders/mftcn1-*")
    step = int(torch.load(workdir / "train_checkpoint.pt", weights_only=True)["step"])
    assert 5 <= step < 60 and not (workdir / "model.pt").exists()
    assert not (home / "results.sqlite").exists() or not ResultStore(home / "results.sqlite").query()
    (workdir / ".train_checkpoint.pt.tmp-99999").write_bytes(b"half a checkpoint")
    dataset_mtimes = {p: p.stat().st_mtime_ns for p in home.glob("datasets/*/*")}

    cli(home, *args)
    record = one_result(home)
    fit = record.config["fit"]
    assert fit["fitted"] and fit["steps"] == 60
    assert fit["resumed_from_step"] >= step  # it went on from a checkpoint, not from step 0
    assert not (workdir / "train_checkpoint.pt").exists() and not list(workdir.glob(".*tmp*"))
    assert {p: p.stat().st_mtime_ns for p in home.glob("datasets/*/*")} == dataset_mtimes


def test_killed_ppo_training_resumes_from_its_checkpoint(tmp_path):
    """swingup with the true state as the embedding (no encoder to train): 10 PPO batches, a checkpoint
    after each; killed after the first, the rerun goes on from the last one."""
    home = tmp_path / "home"
    args = ["run", "--encoder", "true-state", "--task", "swingup", "--preset", "smoke", "--no-progress",
            "--set", "task.dataset.train_episodes=1", "--set", "task.dataset.test_episodes=1",
            "--set", "task.dataset.episode_length=10", "--set", "task.ppo.frames=1600"]
    kill_when(home, args, lambda: bool(list(home.glob("runs/*/ppo_checkpoint.pt"))), timeout=240)
    (checkpoint,) = home.glob("runs/*/ppo_checkpoint.pt")
    state = torch.load(checkpoint, weights_only=True)["state"]
    assert 1 <= state["batch"] < 10
    assert not (home / "results.sqlite").exists() or not ResultStore(home / "results.sqlite").query()

    cli(home, *args)
    record = one_result(home)
    curve = record.curves["train"]
    assert curve["frames"] == [160.0 * (i + 1) for i in range(10)]
    # The batches done before the kill come from the checkpoint, wall-clock readings included: resumed.
    assert curve["wall_s"][:state["batch"]] == state["curve_wall_s"]
    assert curve["return"][:state["batch"]] == state["curve_return"]


def test_killed_sweep_resumes_and_keeps_finished_runs(tmp_path):
    """The whole sweep (driver and its worker processes) is killed after some runs were stored; the rerun
    reuses those and does the rest."""
    home = tmp_path / "home"
    args = ["sweep", "--encoders", "random-state", "--tasks", "cartpole-probe", "--seeds", "0-3", "--workers", "1",
            *SMALL, "--set", "task.probe.epochs=40", "--set", "task.probe.hidden=[64, 64]"]

    def some_runs_stored() -> bool:
        database = home / "results.sqlite"
        return database.exists() and len(ResultStore(database).query()) >= 1

    kill_when(home, args, some_runs_stored, timeout=240, group=True)
    stored = {r.run_id: r.created_at for r in ResultStore(home / "results.sqlite").query()}
    assert 1 <= len(stored) < 4

    out = cli(home, *args).stdout
    assert f"{len(stored)} reused" in out and "0 failed" in out
    store = ResultStore(home / "results.sqlite")
    records = store.query()
    assert len(records) == 4 and len({r.seed for r in records}) == 4 and store.integrity_ok()
    assert {r.run_id: r.created_at for r in records if r.run_id in stored} == stored  # kept, not redone


def test_a_killed_queue_continues_from_its_name_and_exports_every_record(tmp_path):
    """`sweep --queue NAME --export DIR` killed (driver and workers) mid-grid: `sweep status` shows what
    finished and what is left; `sweep --queue NAME` alone continues the recorded grid, redoes nothing that
    finished, and every record ends up in DIR."""
    home, export = tmp_path / "home", tmp_path / "exported"
    args = ["sweep", "--encoders", "random-state", "--tasks", "cartpole-probe", "--seeds", "0-3", "--workers", "1",
            *SMALL, "--set", "task.probe.epochs=40", "--set", "task.probe.hidden=[64, 64]", "--queue", "grid",
            "--export", str(export)]

    kill_when(home, args, lambda: len(list(export.glob("*.json"))) >= 1, timeout=240, group=True)
    stored = {r.run_id: r.created_at for r in ResultStore(home / "results.sqlite").query()}
    assert 1 <= len(stored) < 4 and {p.stem for p in export.glob("*.json")} <= set(stored)
    status = cli(home, "sweep", "status", "--queue", "grid").stdout
    assert f"{len(stored)} done, 0 running, {4 - len(stored)} left, 0 failed" in status, status
    assert "stopped while running" in status and "`mftcn-bench sweep --queue grid` continues it" in status, status

    out = cli(home, "sweep", "--queue", "grid").stdout
    assert f"{len(stored)} reused" in out and "0 failed" in out
    records = ResultStore(home / "results.sqlite").query()
    assert len(records) == 4 and {r.run_id: r.created_at for r in records if r.run_id in stored} == stored
    assert {p.stem for p in export.glob("*.json")} == {r.run_id for r in records}
    assert "4 done, 0 running, 0 left, 0 failed; nothing left to run" in cli(home, "sweep", "status").stdout


def _children(pid: int) -> set[int]:
    """The processes whose parent is `pid` (Linux /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # the process ended while we looked
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from Linux's /proc")
def test_a_sweeps_workers_end_when_its_driver_is_killed(tmp_path):
    """SIGKILL on the sweep's driver alone (not its process group): its worker processes end within seconds
    instead of computing on as orphans; the grid continues later from its queue."""
    home = tmp_path / "home"
    args = ["sweep", "--encoders", "random-state", "--tasks", "cartpole-probe", "--seeds", "0-3", "--workers", "2",
            *SMALL, "--set", "task.probe.epochs=400", "--set", "task.probe.hidden=[64, 64]", "--queue", "grid"]
    proc = subprocess.Popen([sys.executable, "-m", "mftcn_bench.cli", *args], env=env_for(home),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    try:
        while len(_children(proc.pid)) < 3:  # the resource tracker and the two workers
            assert proc.poll() is None and time.monotonic() < deadline, "the sweep never started its workers"
            time.sleep(0.05)
        workers = _children(proc.pid)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    end = time.monotonic() + 15
    while any(_alive(p) for p in workers) and time.monotonic() < end:
        time.sleep(0.1)
    left = [p for p in workers if _alive(p)]
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert not left, f"{len(left)} worker(s) still running after their driver was killed"


# ------------------------------------------------------------------------------------------- concurrency

# Collects with the synthetic collector (the test is about locks, not pixels), logging every episode it
# makes (one line per episode per process), then runs the command line.
COUNTING = """
import os, sys
import mftcn_bench.tasks.probe as probe
from mftcn_bench.data.synthetic import synthetic_collector
def counting(config, index):
    with open(os.environ["COLLECT_LOG"], "a") as log:
        log.write(f"{os.getpid()} {index}\\n")
    return synthetic_collector(config, index)
probe.collect_episode = counting
from mftcn_bench.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_four_concurrent_runs_share_one_dataset_and_lose_no_row(tmp_path):
    home, log = tmp_path / "home", tmp_path / "collect.log"
    tiny_mftcn = ["--encoder", "mftcn1", "--set", "encoder.train.steps=4", "--set", "encoder.train.checkpoint_every=0",
                  "--set", "encoder.model.adapter_channels=8", "--set", "encoder.model.temporal_channels=8",
                  "--set", "encoder.train.batch_timesteps=8"]
    jobs = [  # two runs share one trained encoder (same spec, data, seed): it is fitted once
        [*tiny_mftcn, *SMALL],
        [*tiny_mftcn, *SMALL[:-2], "--set", "task.probe.hidden=[16]"],
        ["--encoder", "random-state", *SMALL, "--seed", "1"],
        ["--encoder", "random-state", *SMALL, "--seed", "2"],
    ]
    env = {**env_for(home), "COLLECT_LOG": str(log)}
    procs = [subprocess.Popen([sys.executable, "-c", COUNTING, "run", *job], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for job in jobs]
    outputs = [proc.communicate(timeout=300) for proc in procs]
    for proc, (_, err) in zip(procs, outputs, strict=True):
        assert proc.returncode == 0, err[-3000:]
        assert "locked" not in err
    store = ResultStore(home / "results.sqlite")
    records = store.query()
    assert len(records) == 4 and len({r.run_id for r in records}) == 4 and store.integrity_ok()
    assert len(list(home.glob("datasets/cartpole-random-*"))) == 1
    collected = log.read_text().split()
    assert sorted(int(i) for i in collected[1::2]) == list(range(EPISODES))  # each episode rendered once
    assert len(set(collected[0::2])) == 1  # by one process
    fits = sorted(r.config["fit"]["fitted"] for r in records if r.encoder == "mftcn1")
    assert fits == [False, True]  # the shared encoder was trained by one run and loaded by the other


def test_a_checkpoint_without_its_completion_marker_is_fitted_again(tmp_path):
    """A plugin's `save` cut off by a kill leaves `model.pt` but no `fit.json`: never taken as finished."""
    from mftcn_bench.core.specs import EncoderSpec
    from mftcn_bench.run.artifacts import _fit_or_load

    class Recording:
        privileged_inputs = ("state", "action")  # nothing withheld: `fit` gets the (here absent) dataset as is

        def __init__(self):
            self.fits, self.loads = 0, 0

        def fit(self, dataset, budget, progress, workdir):
            self.fits += 1
            return {"final_loss": 0.5}

        def save(self, path):
            path.write_bytes(b"complete")

        def load(self, path):
            assert path.read_bytes() == b"complete"
            self.loads += 1

    spec = EncoderSpec("fake", "fake", "test", train={"steps": 1})
    workdir = tmp_path / "enc"
    workdir.mkdir()
    (workdir / "model.pt").write_bytes(b"half")  # the kill came during save
    encoder = Recording()
    first = _fit_or_load(encoder, spec, None, workdir, False)
    assert first["fitted"] and encoder.fits == 1 and (workdir / "fit.json").exists()
    again = _fit_or_load(encoder, spec, None, workdir, False)
    assert again["reused"] and encoder.fits == 1 and encoder.loads == 1


def test_an_exported_run_continues_in_another_home_to_the_uninterrupted_result(tmp_path):
    """The machine dies after the first PPO checkpoint: `runs export` moves the run's folder to a directory,
    `runs import` puts it into an empty home, and the same command finishes it there to the metrics (wall
    clock aside) and curves of a run that was never interrupted."""
    args = ["run", "--encoder", "true-state", "--task", "swingup", "--preset", "smoke", "--no-progress",
            "--set", "task.dataset.train_episodes=1", "--set", "task.dataset.test_episodes=1",
            "--set", "task.dataset.episode_length=10", "--set", "task.ppo.frames=1600"]
    first, second, straight = tmp_path / "first", tmp_path / "second", tmp_path / "straight"
    kill_when(first, args, lambda: bool(list(first.glob("runs/*/ppo_checkpoint.pt"))), timeout=240)
    (run_dir,) = (p.parent for p in first.glob("runs/*/ppo_checkpoint.pt"))
    done = torch.load(run_dir / "ppo_checkpoint.pt", weights_only=True)["state"]["batch"]
    assert 1 <= done < 10

    exported = cli(first, "runs", "export", run_dir.name, str(tmp_path / "moved"))
    assert f"runs import {tmp_path / 'moved' / run_dir.name}" in exported.stdout
    imported = cli(second, "runs", "import", str(tmp_path / "moved" / run_dir.name))
    assert "reads no data, so it continues" in imported.stdout
    cli(second, *args)
    cli(straight, *args)
    moved, uninterrupted = one_result(second), one_result(straight)
    assert moved.run_id == uninterrupted.run_id == run_dir.name
    wall_clock = {"train_wall_s", "train_fps"}
    assert {k: v for k, v in moved.metrics.items() if k not in wall_clock} == \
           {k: v for k, v in uninterrupted.metrics.items() if k not in wall_clock}
    assert moved.curves["train"]["return"] == uninterrupted.curves["train"]["return"]
    assert moved.curves["test"] == uninterrupted.curves["test"]
    # the batches before the death were trained in the first home: their wall-clock readings came along
    first_wall = done and moved.curves["train"]["wall_s"][:done]
    assert first_wall == [float(w) for w in torch.load(tmp_path / "moved" / run_dir.name / "run" / "ppo_checkpoint.pt",
                                                        weights_only=True)["state"]["curve_wall_s"]]
