"""A sweep's queue file: the grid it refuses to mix, and `sweep status` (done / running / left, time left)."""

from __future__ import annotations

import json
import os
import subprocess
from dataclasses import replace

import pytest

from mftcn_bench.core.fileio import exclusive_lock
from mftcn_bench.orchestration.queue import (
    PPO_FRAMES_METRIC,
    PPO_WALL_METRIC,
    QueueError,
    SweepQueue,
    queue_status,
)
from mftcn_bench.orchestration.sweep import SweepJob, SweepRequest, SweepStage
from tests.records import make_record

GRID = SweepRequest(("a", "b"), ("t",), (0, 1), "quick", workers=2)


def _jobs(*run_ids: str) -> list[SweepJob]:
    return [SweepJob(e, "t", s, "quick", run_id=r) for (e, s), r in zip((("a", 0), ("a", 1), ("b", 0), ("b", 1)),
                                                                        run_ids, strict=True)]


def test_status_counts_done_running_left_and_estimates_the_time_left_from_finished_jobs(home):
    from mftcn_bench.results.store import ResultStore

    queue = SweepQueue.open(home, "grid", GRID)
    queue.jobs_changed(_jobs("r0", "r1", "r2", "r3"))
    store = ResultStore(home.database)
    for run_id, seconds in (("r0", 100.0), ("r1", 300.0)):
        store.put(replace(make_record("a", "t", 0, {"m": 1.0}), run_id=run_id, timings={"total_s": seconds}))
    now = 1_000_000.0
    lock = home.runs / ".r2.lock"
    with exclusive_lock(lock):  # a process is running r2, started 50 s ago
        os.utime(lock, (now - 50, now - 50))
        status = queue_status(home, "grid", now=now)
    assert status.counts == {"done": 2, "running": 1, "left": 1, "failed": 0}
    assert [r["state"] for r in status.rows] == ["done", "done", "running", "left"]
    # A job of task t takes 200 s (the mean of the finished): r2 has 150 s to go, r3 200 s on the free worker.
    assert status.left_s == pytest.approx(200)
    assert "2 done, 1 running, 1 left, 0 failed; about 0 h 03 min left at 2 job(s) at once" in status.summary()
    assert queue_status(home, "grid", now=now).counts["running"] == 0, "the lock was released"


def test_status_says_how_far_an_unfinished_runs_ppo_got_by_its_checkpoint(home):
    """A running or killed control run's last checkpoint (`rl.checkpoint_progress`): its frames and the
    last batch's training return; nothing for a run without one (not started, or no PPO)."""
    import torch

    queue = SweepQueue.open(home, "grid", GRID)
    queue.jobs_changed(_jobs("r0", "r1", "r2", "r3"))
    run_dir = home.runs / "r1"
    run_dir.mkdir(parents=True)
    torch.save({"state": {"frames": 2_320_000, "curve_return": [500.0, 528.75]}}, run_dir / "ppo_checkpoint.pt")
    rows = queue_status(home, "grid").rows
    assert [r["checkpointed"] for r in rows] == ["", "2.32 M frames, training return 529", "", ""]


def test_the_time_left_counts_each_job_at_its_encoders_measured_time(home):
    """a's jobs take 100 s, b's 400 s on the same task: a's job left takes 100 s, not the task's mean of 300."""
    from mftcn_bench.results.store import ResultStore

    queue = SweepQueue.open(home, "grid", GRID)
    queue.jobs_changed(_jobs("r0", "r1", "r2", "r3"))
    store = ResultStore(home.database)
    for encoder, run_id, seconds in (("a", "r0", 100.0), ("b", "r2", 400.0), ("b", "r3", 400.0)):
        store.put(replace(make_record(encoder, "t", 0, {"m": 1.0}), run_id=run_id, timings={"total_s": seconds}))
    assert queue_status(home, "grid").left_s == pytest.approx(100)  # r1, a's, alone on one of two workers


def test_a_resumed_run_counts_its_ppo_clock_over_every_process(home):
    """A control run finished by a second process has timings of that process only (394 s here); its PPO
    clock, kept in the checkpoint, counts every process (2,004 s), so the job's cost is the clock's."""
    from mftcn_bench.results.store import ResultStore

    queue = SweepQueue.open(home, "grid", GRID)
    queue.jobs_changed(_jobs("r0", "r1", "r2", "r3"))
    metrics = {"return_mean": 315.0, PPO_WALL_METRIC: 2004.0, PPO_FRAMES_METRIC: 3_008_000.0}
    timings = {"dataset_s": 1.0, "fit_s": 0.0, "evaluate_s": 393.0, "total_s": 394.0}
    ResultStore(home.database).put(replace(make_record("a", "t", 0, metrics), run_id="r0", timings=timings))
    status = queue_status(home, "grid")
    assert status.left_s == pytest.approx(2 * 2005.0)  # r1, r2, r3 at a's measured cost: r3 after r1 or r2


def test_an_unfinished_run_counts_the_frames_past_its_checkpoint(home):
    """r1 runs again from a checkpoint at half its frames and r2 waits at 80%: they have half and a fifth
    of a finished run's 1,000 s to go, whatever the lock's age says (a resumed run's clock restarts)."""
    import torch

    from mftcn_bench.results.store import ResultStore

    queue = SweepQueue.open(home, "grid", GRID)
    queue.jobs_changed(_jobs("r0", "r1", "r2", "r3"))
    metrics = {"return_mean": 600.0, PPO_WALL_METRIC: 900.0, PPO_FRAMES_METRIC: 3_000_000.0}
    ResultStore(home.database).put(replace(make_record("a", "t", 0, metrics), run_id="r0",
                                           timings={"total_s": 1000.0}))
    for run_id, frames in (("r1", 1_500_000), ("r2", 2_400_000)):
        (home.runs / run_id).mkdir(parents=True)
        torch.save({"state": {"frames": frames, "curve_return": [500.0]}}, home.runs / run_id / "ppo_checkpoint.pt")
    now = 1_000_000.0
    lock = home.runs / ".r1.lock"
    with exclusive_lock(lock):  # running for 10 s since this process took it
        os.utime(lock, (now - 10, now - 10))
        status = queue_status(home, "grid", now=now)
    assert [r["state"] for r in status.rows] == ["done", "running", "left", "left"]
    # r1 holds a worker for 500 s; r2 (200 s) then r3 (1,000 s) take the other: 1,200 s, not (500+200+1000)/2.
    assert status.left_s == pytest.approx(200 + 1000)


def test_without_a_finished_job_the_status_says_it_cannot_estimate(home):
    SweepQueue.open(home, "grid", GRID)  # recorded, not yet planned: the grid as requested
    status = queue_status(home, "grid")
    assert status.counts == {"done": 0, "running": 0, "left": 4, "failed": 0} and status.left_s is None
    assert "no finished job yet" in status.summary()


def test_a_queue_keeps_its_grid_and_export_folder(home, tmp_path):
    SweepQueue.open(home, "grid", GRID, tmp_path / "out")
    again = SweepQueue.open(home, "grid")
    assert again.request == GRID and again.export == (tmp_path / "out").resolve()
    assert SweepQueue.open(home, "grid", replace(GRID, workers=5)).request.workers == 5
    with pytest.raises(QueueError, match="holds another grid \\(seeds differ\\)"):
        SweepQueue.open(home, "grid", SweepRequest(("a", "b"), ("t",), (0, 1, 2), "quick"))
    with pytest.raises(QueueError, match="no queue 'other'"):
        SweepQueue.open(home, "other")
    with pytest.raises(QueueError, match="plain file name"):
        SweepQueue.open(home, "../x", GRID)
    data = json.loads((home.root / "queues" / "grid.json").read_text())
    assert data["request"]["seeds"] == [0, 1] and data["export"] == str((tmp_path / "out").resolve())


def _set_stage(home, **fields):
    path = home.root / "queues" / "grid.json"
    data = json.loads(path.read_text())
    data["stage"].update(fields)
    path.write_text(json.dumps(data))


def test_status_counts_the_fits_before_the_first_run_at_their_measured_pace(home):
    from mftcn_bench.results.store import ResultStore

    queue = SweepQueue.open(home, "grid", GRID)
    queue.jobs_changed(_jobs("r0", "r1", "r2", "r3"))
    ResultStore(home.database).put(replace(make_record("a", "t", 0, {"m": 1.0}), run_id="r0",
                                           timings={"total_s": 100.0}))
    queue.stage_changed(SweepStage("encoder", 0, 8))
    status = queue_status(home, "grid")
    assert ("now fitting encoders, 0 of 8 done (their time is not in the estimate until one that is not reused "
            "finishes)") in status.summary() and status.stage_left_s is None
    queue.stage_changed(SweepStage("encoder", 1, 8, worked=0, worked_s=0.0))  # a fit of an earlier start
    assert queue_status(home, "grid").stage_left_s is None
    now = 1_000_000.0
    queue.stage_changed(SweepStage("encoder", 3, 8, worked=2, worked_s=480.0))  # 240 s a fit, 2 at once
    _set_stage(home, updated_at=now - 60)
    status = queue_status(home, "grid", now=now)
    assert status.stage_left_s == pytest.approx(240 * 5 / 2 - 60)
    assert status.left_s == pytest.approx(2 * 100)  # the runs: three left of 100 s, two at once
    assert ("1 done, 0 running, 3 left, 0 failed; now fitting encoders, 3 of 8 done, about 0 h 09 min left for "
            "them; about 0 h 12 min left at 2 job(s) at once") in status.summary()


def test_status_tells_a_stopped_queue_from_a_running_one(home):
    queue = SweepQueue.open(home, "grid", GRID)
    queue.jobs_changed(_jobs("r0", "r1", "r2", "r3"))
    queue.stage_changed(SweepStage("encoder", 3, 8))
    assert "now fitting encoders, 3 of 8 done" in queue_status(home, "grid").summary()  # this process: alive
    ended = subprocess.Popen(["true"])
    ended.wait()
    _set_stage(home, pid=ended.pid)
    assert ("stopped while fitting encoders, 3 of 8 done; `mftcn-bench sweep --queue grid` continues it"
            in queue_status(home, "grid").summary())


@pytest.mark.parametrize(("running", "left", "workers", "expected"), [
    ([6120.0, 15120.0], [], 2, 15120.0),        # the tail of a queue: the longest job, not the mean
    ([], [100.0, 100.0, 100.0], 2, 200.0),      # the third starts when the first worker frees
    ([50.0], [100.0, 30.0], 2, 100.0),          # 100 on the free worker; 30 after the running one's 50
    ([], [100.0, 100.0], 1, 200.0),
    ([], [], 2, 0.0),
    ([10.0, 20.0, 30.0], [5.0], 2, 30.0),       # more running than workers (a restart with fewer)
])
def test_the_time_left_is_the_makespan_of_the_workers_taking_jobs_in_order(running, left, workers, expected):
    from mftcn_bench.orchestration.queue import _makespan

    assert _makespan(running, left, workers) == pytest.approx(expected)
