"""A sweep's grid recorded in the home (`<home>/queues/<name>.json`), for long grids on one machine.

`mftcn-bench sweep ... --queue NAME` writes the grid and each job's state there as the sweep goes, and
exports each record as it is stored (`--export DIR`); started again after the process or the session was
killed (`sweep --queue NAME`, the grid read back), the sweep skips finished runs and continues unfinished
ones from their checkpoints (`run.runner`). `mftcn-bench sweep status --queue NAME` reads the file and the
home: a job is done when the store holds its run id, running while a process holds the run's lock
(`runs/.<id>.lock`), an unfinished control run shows the frames of its last PPO checkpoint, and the time
left is estimated from the measured times of the queue's finished jobs of the same encoder and task, an
unfinished control run counted for the part of its PPO frames its checkpoint has still to train, as the
wall time until the last job ends with the queue's workers taking the jobs left in order.
The file also holds the sweep's stage (data sets, encoder fits, runs: `SweepStage`) and which process
drives it, so that the status can say how far the fits before the first run got, count their time left
at the pace of those that did their work (a fit reused from an earlier start takes none and says nothing
of it), and tell a stopped queue from a running one.
"""

from __future__ import annotations

import fcntl
import heapq
import json
import os
import socket
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.fileio import atomic_write_bytes, exclusive_lock
from mftcn_bench.core.home import BenchHome
from mftcn_bench.orchestration.sweep import SweepJob, SweepRequest, SweepStage
from mftcn_bench.results.records_io import record_to_json
from mftcn_bench.results.store import ResultStore, RunRecord
from mftcn_bench.rl.checkpoint_progress import CheckpointProgress, checkpoint_progress

_GRID_KEYS = ("encoders", "tasks", "seeds", "preset", "overrides", "device", "deterministic")  # what a grid is
# A control run's metrics (`tasks.control`): PPO's own clock, summed over every process that trained it (a run
# resumed from its checkpoint has timings of its last process only), and the frames it trained.
PPO_WALL_METRIC, PPO_FRAMES_METRIC = "train_wall_s", "frames"


class QueueError(SpecError):
    """A queue name that does not fit the request (another grid under that name, or no grid to continue)."""


def queue_path(home: BenchHome, name: str) -> Path:
    if not name or "/" in name or name.startswith("."):
        raise QueueError(f"--queue {name!r}: a queue name is a plain file name (letters, digits, - and _)")
    return home.root / "queues" / f"{name}.json"


def _request_json(request: SweepRequest) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(request)))  # tuples as lists, as the file reads back


def request_from_json(data: dict[str, Any]) -> SweepRequest:
    return SweepRequest(tuple(data["encoders"]), tuple(data["tasks"]), tuple(data["seeds"]), data["preset"],
                        tuple((k, v) for k, v in data["overrides"]), data["executor"], data["address"],
                        int(data["workers"]), int(data["threads"]), data["device"], bool(data["deterministic"]))


class SweepQueue:
    """One named queue: its grid, export folder and the latest state of its jobs (a `SweepListener`)."""

    def __init__(self, home: BenchHome, name: str, request: SweepRequest, export: Path | None) -> None:
        self.home, self.name, self.request, self.export = home, name, request, export
        self.path = queue_path(home, name)
        self._jobs: list[dict[str, Any]] = []
        self._stage: dict[str, Any] | None = None

    @classmethod
    def open(cls, home: BenchHome, name: str, request: SweepRequest | None = None,
             export: Path | None = None) -> SweepQueue:
        """The queue `name`: created with `request`, or read back (then `request`, if given, must be its
        grid: the same encoders, tasks, seeds, preset, overrides and device)."""
        path = queue_path(home, name)
        if not path.exists():
            if request is None:
                raise QueueError(f"no queue {name!r} in {path.parent}; give --encoders and --tasks to start it")
            queue = cls(home, name, request, export)
            queue.jobs_changed([])
            return queue
        cls.check(home, name, request)
        data = json.loads(path.read_text(encoding="utf-8"))
        stored = request_from_json(data["request"]) if request is None else request  # workers etc.: this start's
        recorded = data.get("export")
        queue = cls(home, name, stored, export or (Path(recorded) if recorded else None))
        queue._jobs = data["jobs"]  # kept until this start's sweep reports its own
        return queue

    @staticmethod
    def check(home: BenchHome, name: str, request: SweepRequest | None) -> None:
        """Refuse, before any work, a name that is no plain file name or that holds another grid."""
        path = queue_path(home, name)
        if request is None or not path.exists():
            return
        theirs, mine = json.loads(path.read_text(encoding="utf-8"))["request"], _request_json(request)
        differs = [k for k in _GRID_KEYS if mine[k] != theirs[k]]
        if differs:
            raise QueueError(f"queue {name!r} holds another grid ({', '.join(differs)} differ); continue it "
                             f"with `sweep --queue {name}` alone, or start a new queue under another name")

    def jobs_changed(self, jobs: Sequence[SweepJob]) -> None:
        self._jobs = [asdict(job) for job in jobs]
        self._write()

    def stage_changed(self, stage: SweepStage) -> None:
        self._stage = {**asdict(stage), "updated_at": time.time(), "pid": os.getpid(),
                       "host": socket.gethostname()}
        self._write()

    def _write(self) -> None:
        with exclusive_lock(self.path.with_suffix(".lock")):
            data = {"name": self.name, "request": _request_json(self.request),
                    "export": None if self.export is None else str(self.export.resolve()),
                    "updated_at": datetime.now(UTC).isoformat(timespec="seconds"),
                    "stage": self._stage, "jobs": self._jobs}
            atomic_write_bytes(self.path, json.dumps(data, indent=1).encode())

    def record_stored(self, record: RunRecord) -> None:
        if self.export is not None:
            self.export.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(self.export / f"{record.run_id}.json", record_to_json(record))


def _running_since(lock: Path) -> float | None:
    """When the process holding the run's lock took it (the lock file is opened, so touched, by it), or
    None when no process holds it."""
    if not lock.exists():
        return None
    with open(lock) as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return lock.stat().st_mtime
        fcntl.flock(handle, fcntl.LOCK_UN)
    return None


_STAGE_NAMES = {"dataset": "building data sets", "encoder": "fitting encoders", "run": "running"}


def _driver_alive(stage: dict[str, Any]) -> bool:
    """Whether the process that wrote the stage still runs (assumed so when it ran on another host)."""
    if stage.get("host") != socket.gethostname():
        return True
    try:
        os.kill(int(stage["pid"]), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _stage_progress(name: str, stage: dict[str, Any] | None, now: float,
                    workers: int) -> tuple[str | None, float | None]:
    """A phrase on the sweep's stage (None when there is nothing to add to the jobs' rows) and the time its
    data sets or fits still need at the pace of those that did their work (None: not measured yet, or not
    such a stage)."""
    if not stage:
        return None, None
    kind, done, total = stage["kind"], int(stage["done"]), int(stage["total"])
    what = f"{_STAGE_NAMES[kind]}, {done} of {total} done"
    if not _driver_alive(stage):
        return f"stopped while {what}; `mftcn-bench sweep --queue {name}` continues it", None
    if kind == "run" or done >= total:
        return None, None
    worked = int(stage.get("worked", 0))  # absent in the files of drivers older than the field
    if not worked:
        return f"now {what} (their time is not in the estimate until one that is not reused finishes)", None
    pace = float(stage["worked_s"]) / worked / max(1, workers)
    return f"now {what}", max(0.0, pace * (total - done) - (now - float(stage["updated_at"])))


def _job_seconds(record: RunRecord, fallback: float) -> float:
    """What a finished job cost: its record's total time or, for a run resumed from its PPO checkpoint
    (whose timings cover the last process only), its data and fit times plus PPO's clock over every process."""
    total = float(record.timings.get("total_s", fallback))
    ppo_wall = record.metrics.get(PPO_WALL_METRIC)
    if ppo_wall is None:
        return total
    return max(total, float(record.timings.get("dataset_s", 0.0)) + float(record.timings.get("fit_s", 0.0))
               + float(ppo_wall))


def _makespan(running: Sequence[float], left: Sequence[float], workers: int) -> float:
    """The wall time until the last job ends: each running job holds a worker for its time left, and the
    jobs left start in order on the first worker to come free (the pool's order). Not the sum over the
    workers: two jobs of 1.7 h and 4.2 h left on two workers take 4.2 h, not 3 h."""
    ends = sorted(running) + [0.0] * max(0, max(1, workers) - len(running))
    heapq.heapify(ends)
    for seconds in left:
        heapq.heappush(ends, heapq.heappop(ends) + seconds)
    return max(ends, default=0.0)


def _checkpointed(progress: CheckpointProgress | None) -> str:
    """How far an unfinished run's PPO got by its last checkpoint ("" without one: not started, or no PPO)."""
    if progress is None:
        return ""
    text = f"{progress.frames / 1e6:.2f} M frames"
    return text if progress.last_return is None else f"{text}, training return {progress.last_return:.0f}"


def _hours(seconds: float) -> str:
    hours, minutes = divmod(round(seconds / 60), 60)
    return f"{hours} h {minutes:02d} min"


@dataclass(frozen=True)
class QueueStatus:
    """What `sweep status` prints: one row per job, the counts, the sweep's stage, and the time left."""

    rows: list[dict[str, Any]]
    counts: dict[str, int]
    left_s: float | None  # the runs' time left; None: no finished job of the queue to estimate from
    workers: int
    stage: str | None = None  # fits before the first run, or a stopped driver (`_stage_progress`)
    stage_left_s: float | None = None  # the time the stage's data sets or fits still need

    def summary(self) -> str:
        counts = ", ".join(f"{n} {state}" for state, n in self.counts.items())
        if not self.counts["left"] and not self.counts["running"]:
            return f"{counts}; nothing left to run"
        parts = [counts]
        if self.stage:
            parts.append(self.stage + ("" if self.stage_left_s is None else
                                       f", about {_hours(self.stage_left_s)} left for them"))
        if self.left_s is None:
            parts.append("no finished job yet to estimate the time left from")
        else:
            parts.append(f"about {_hours(self.left_s + (self.stage_left_s or 0.0))} left at {self.workers} "
                         f"job(s) at once (from the measured times of the finished jobs)")
        return "; ".join(parts)


def queue_status(home: BenchHome, name: str, now: float | None = None) -> QueueStatus:
    """The state of every job of the queue `name`, from its file, the store and the runs' locks."""
    path = queue_path(home, name)
    if not path.exists():
        raise QueueError(f"no queue {name!r} in {path.parent}")
    data = json.loads(path.read_text(encoding="utf-8"))
    now = time.time() if now is None else now
    store = ResultStore(home.database)
    jobs = [SweepJob(**job) for job in data["jobs"]]
    if not jobs:  # planned, not started: the grid as requested
        request = request_from_json(data["request"])
        jobs = [SweepJob(e, t, s, request.preset or "-") for e in request.encoders for t in request.tasks
                for s in request.seeds]
    states, measured, since, task_frames = [], {}, {}, {}
    for job in jobs:
        record = store.get(job.run_id) if job.run_id else None
        started = _running_since(home.runs / f".{job.run_id}.lock") if job.run_id else None
        if record is not None:
            state = "done"
            measured.setdefault((job.encoder, job.task), []).append(_job_seconds(record, job.seconds))
            if PPO_FRAMES_METRIC in record.metrics and PPO_WALL_METRIC in record.metrics:
                task_frames[job.task] = max(task_frames.get(job.task, 0.0), float(record.metrics[PPO_FRAMES_METRIC]))
        elif started is not None:
            state, since[id(job)] = "running", started
        elif job.status == "failed":
            state = "failed"
        else:
            state = "left"
        states.append(state)
    progress = {id(j): checkpoint_progress(home.runs / j.run_id) if j.run_id and s != "done" else None
                for j, s in zip(jobs, states, strict=True)}
    every = [s for times in measured.values() for s in times]
    left_s = None
    if every:
        def expected(job: SweepJob) -> float:
            """The mean time of the finished jobs of its encoder and task, else of its task, else of all:
            encoders' costs differ many times over (a random-state control run renders, true state does not)."""
            times = measured.get((job.encoder, job.task)) or [
                t for (_, task), ts in measured.items() if task == job.task for t in ts] or every
            return sum(times) / len(times)

        def remaining(job: SweepJob, state: str) -> float:
            """A job's time still to go: the part of its PPO frames past its checkpoint when it has one and
            a finished run of its task says how many it trains (a resumed run's clock started at the
            checkpoint, not at 0), else what is left of its expected time."""
            checkpoint, frames = progress[id(job)], task_frames.get(job.task)
            if checkpoint is not None and frames:
                return expected(job) * max(0.0, 1.0 - checkpoint.frames / frames)
            return max(0.0, expected(job) - (now - since[id(job)])) if state == "running" else expected(job)

        left_s = _makespan([remaining(j, s) for j, s in zip(jobs, states, strict=True) if s == "running"],
                           [remaining(j, s) for j, s in zip(jobs, states, strict=True) if s == "left"],
                           int(data["request"]["workers"]))
    stage, stage_left_s = _stage_progress(name, data.get("stage"), now, int(data["request"]["workers"]))
    rows = [{"encoder": j.encoder, "task": j.task, "seed": j.seed, "state": s, "run id": j.run_id or "-",
             "running for": f"{(now - since[id(j)]) / 60:.0f} min" if s == "running" else "",
             "checkpointed": _checkpointed(progress[id(j)]),
             "error": (j.error or "") if s == "failed" else ""}
            for j, s in zip(jobs, states, strict=True)]
    counts = {state: states.count(state) for state in ("done", "running", "left", "failed")}
    return QueueStatus(rows, counts, left_s, int(data["request"]["workers"]), stage, stage_left_s)
