"""Sweeps: a grid of encoders x tasks x seeds, run on a local process pool or on Ray.

Order of work: every name, preset and override is checked before anything starts. Then the shared
prerequisites are built once each, before the fan-out: the datasets (one job per distinct dataset), then
the trained encoders (one job per distinct checkpoint). Runs already in the store (same run id) are
reused, not redone, so an interrupted sweep continues where it stopped. Each remaining (encoder, task,
seed) is one job; its worker returns the RunRecord and the driver writes it into its own store, so
results reach the driver's store even from cluster workers that do not share its disk.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC, datetime
from typing import Any, Protocol

from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.core.home import BenchHome
from mftcn_bench.data.dataset import find_dataset
from mftcn_bench.orchestration.executors import Executor, check_executor_args, make_executor
from mftcn_bench.orchestration.jobs import JobKind, JobResult, JobSpec
from mftcn_bench.results.store import ResultStore, RunRecord
from mftcn_bench.run.plan import PreparedRun, RunRequest, encoder_key_of, prepare, run_id_of


class SweepFailed(BenchError):
    """Some jobs of a sweep failed (the others finished and are stored)."""

    exit_code = 1


@dataclass(frozen=True)
class SweepRequest:
    encoders: tuple[str, ...]
    tasks: tuple[str, ...]
    seeds: tuple[int, ...]
    preset: str | None = None
    overrides: tuple[tuple[str, Any], ...] = ()
    executor: str = "local"
    address: str | None = None
    workers: int = 2
    threads: int = 1
    device: str = "auto"
    deterministic: bool = False


@dataclass
class SweepJob:
    """One (encoder, task, seed) of the grid and what became of it: planned, done, reused or failed."""

    encoder: str
    task: str
    seed: int
    preset: str
    status: str = "planned"
    run_id: str | None = None
    error: str | None = None
    seconds: float = 0.0
    metrics: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SweepStage:
    """Which stage a sweep is in (building datasets, fitting encoders, running) and how many of that stage's
    jobs are done: until the runs start, the jobs' states alone do not say how far a sweep got."""

    kind: JobKind
    done: int
    total: int
    worked: int = 0  # of the done jobs, those that did the work (not reused from an earlier start) ...
    worked_s: float = 0.0  # ... and their seconds: a reused fit takes none and says nothing of the pace


class SweepListener(Protocol):
    """Told of each change of the jobs' states, of each stage's progress and of each record the driver
    stores (a queue keeps them in the home and exports the records: `orchestration.queue`)."""

    def jobs_changed(self, jobs: Sequence[SweepJob]) -> None: ...

    def stage_changed(self, stage: SweepStage) -> None: ...

    def record_stored(self, record: RunRecord) -> None: ...


def parse_names(text: str, what: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    if not names:
        raise SpecError(f"--{what} needs at least one name (comma-separated)")
    return names


def parse_seeds(text: str) -> tuple[int, ...]:
    """`0-4` -> 0..4; `0,2,7`; `0-2,5`."""
    seeds: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        low, dash, high = part.partition("-")
        try:
            first = int(low)
            last = int(high) if dash else first
        except ValueError:
            raise SpecError(f"--seeds {text!r}: expected non-negative integers and ranges like 0-4 or 0,2,5") \
                from None
        if first < 0 or last < first:
            raise SpecError(f"--seeds {text!r}: ranges go from a non-negative low to a high, like 0-4")
        seeds.extend(range(first, last + 1))
    return tuple(dict.fromkeys(seeds))


class Sweep:
    """A validated sweep: `plan()` builds prerequisites and finds reusable runs, `run()` does the rest."""

    def __init__(self, request: SweepRequest, home: BenchHome, echo: Callable[[str], None] = print,
                 listener: SweepListener | None = None) -> None:
        check_executor_args(request.executor, request.workers, request.address)
        if not request.seeds:
            raise SpecError("--seeds needs at least one seed")
        if request.threads < 1:
            raise SpecError(f"--threads must be >= 1, got {request.threads}")
        self.request, self.home, self.echo, self.listener = request, home, echo, listener
        self.prepared: list[PreparedRun] = [  # the runs' plans, without encoders: the workers build their own
            prepare(RunRequest(e, t, request.preset, s, request.overrides, device=request.device,
                               deterministic=request.deterministic))
            for e in request.encoders for t in request.tasks for s in request.seeds
        ]
        self.jobs = [SweepJob(p.request.encoder, p.request.task, p.request.seed, p.preset) for p in self.prepared]
        self.store = ResultStore(home.database)
        # Cluster workers use their own home; local ones (pool or local Ray) share the driver's.
        self.worker_home = None if request.address else str(home.root)

    def _spec(self, kind: JobKind, prepared: PreparedRun, index: int = 0) -> JobSpec:
        r = prepared.request
        return JobSpec(kind, r.encoder, r.task, r.preset, r.seed, tuple(r.overrides), self.worker_home,
                       self.request.threads, self._job_device(prepared, index), r.deterministic)

    def _job_device(self, prepared: PreparedRun, index: int) -> str:
        """The device a job asks for: the CPU, or on a GPU machine the driver's GPUs in turn (a local pool
        of more workers than GPUs shares them; the index is not part of a run's identity). A Ray task asks
        for one GPU and sees only the one Ray gives it, as cuda:0."""
        placement = prepared.placement
        if not placement.is_cuda:
            return "cpu"
        if self.request.executor == "ray" or ":" in prepared.request.device:
            return "cuda" if self.request.executor == "ray" else placement.device
        import torch

        return f"cuda:{index % max(1, torch.cuda.device_count())}"

    def _phase(self, executor: Executor, kind: JobKind, groups: dict[str, list[int]]) -> dict[str, JobResult]:
        """One job per group (its first member's), results by group key."""
        keys = list(groups)
        specs = [self._spec(kind, self.prepared[groups[k][0]], n) for n, k in enumerate(keys)]
        results: dict[str, JobResult] = {}
        worked: list[JobResult] = []  # the results of the jobs that did their work (`SweepStage.worked`)
        self._stage(SweepStage(kind, 0, len(specs)))
        for n, (i, result) in enumerate(executor.map(specs), 1):
            results[keys[i]] = result
            if result.ok and not result.reused:
                worked.append(result)
            self._stage(SweepStage(kind, n, len(specs), len(worked), sum(r.seconds for r in worked)))
            job = self.jobs[groups[keys[i]][0]]
            state = "ok" if result.ok else f"FAILED: {result.error}"
            self.echo(f"[{kind} {n}/{len(specs)}] {job.task}" + (f" {job.encoder} seed {job.seed}"
                      if kind == "encoder" else "") + f": {state} ({result.seconds:.1f} s)")
        return results

    def _fail(self, index: int, error: str) -> None:
        self.jobs[index].status, self.jobs[index].error = "failed", error

    def _stage(self, stage: SweepStage) -> None:
        if self.listener is not None and stage.total:
            self.listener.stage_changed(stage)

    def _changed(self) -> None:
        if self.listener is not None:
            self.listener.jobs_changed(self.jobs)

    def _store(self, record: RunRecord) -> None:
        """Write a worker's record into the driver's store and runs folder (if not there already)."""
        if self.store.get(record.run_id) is None:
            if not record.created_at:
                record = replace(record, created_at=datetime.now(UTC).isoformat(timespec="seconds"))
            self.store.put(record)
        run_dir = self.home.runs / record.run_id
        if not (run_dir / "result.json").exists():
            run_dir.mkdir(parents=True, exist_ok=True)
            stored = self.store.get(record.run_id) or record
            atomic_write_bytes(run_dir / "result.json", json.dumps(asdict(stored), indent=1, sort_keys=True).encode())
        if self.listener is not None:
            self.listener.record_stored(self.store.get(record.run_id) or record)

    def run(self, executor: Executor | None = None) -> list[SweepJob]:
        own = executor is None
        executor = executor or make_executor(self.request.executor, self.request.workers, self.request.address)
        try:
            self._run(executor)
        finally:
            if own:
                executor.close()
        return self.jobs

    def _run(self, executor: Executor) -> None:
        # 1. datasets: one job per distinct dataset config (reusing what the driver's home already has)
        fingerprints: dict[int, str | None] = {}
        by_dataset: dict[str, list[int]] = {}
        for i, p in enumerate(self.prepared):
            local = find_dataset(self.home.datasets, p.task.dataset_config, p.task.collector) \
                if self.worker_home and p.reads_data else None
            if not p.reads_data:  # nothing to collect (`PreparedRun.reads_data`)
                fingerprints[i] = None
            elif local is not None:
                fingerprints[i] = local.fingerprint
            else:
                by_dataset.setdefault(p.dataset_key, []).append(i)
        for key, result in self._phase(executor, "dataset", by_dataset).items():
            for i in by_dataset[key]:
                if result.ok and result.fingerprint:
                    fingerprints[i] = result.fingerprint
                else:
                    self._fail(i, f"dataset: {result.error}")
        # 2. finished runs are reused
        todo = []
        for i, p in enumerate(self.prepared):
            if i not in fingerprints:
                continue
            run_id = run_id_of(p, fingerprints[i])
            stored = self.store.get(run_id)
            self.jobs[i].run_id = run_id
            if stored is not None:
                self.jobs[i].status, self.jobs[i].metrics = "reused", stored.metrics
                if self.listener is not None:
                    self.listener.record_stored(stored)
            else:
                todo.append(i)
        self._changed()
        # 3. trained encoders: one job per distinct checkpoint (encoders that train nothing need none)
        by_encoder: dict[str, list[int]] = {}
        for i in todo:
            if not self.prepared[i].needs_fit:
                continue
            by_encoder.setdefault(encoder_key_of(self.prepared[i], fingerprints[i]), []).append(i)
        for key, result in self._phase(executor, "encoder", by_encoder).items():
            if not result.ok:
                for i in by_encoder[key]:
                    self._fail(i, f"encoder: {result.error}")
        self._changed()
        # 4. the runs
        runs = [i for i in todo if self.jobs[i].status == "planned"]
        specs = [self._spec("run", self.prepared[i], n) for n, i in enumerate(runs)]
        self._stage(SweepStage("run", 0, len(specs)))
        for n, (k, result) in enumerate(executor.map(specs), 1):
            self._stage(SweepStage("run", n, len(specs)))
            job = self.jobs[runs[k]]
            job.seconds = result.seconds
            if result.ok and result.record is not None:
                self._store(result.record)
                job.status = "reused" if result.reused else "done"
                job.run_id, job.metrics = result.record.run_id, result.record.metrics
            else:
                self._fail(runs[k], result.error or "no result")
            self._changed()
            self.echo(f"[run {n}/{len(specs)}] {job.encoder} on {job.task} seed {job.seed}: {job.status}"
                      + (f" ({job.error})" if job.error else f" ({job.seconds:.1f} s)"))


def summary_rows(jobs: Sequence[SweepJob], metric_of: Callable[[str], str | None] = lambda task: None,
                 ) -> list[dict[str, Any]]:
    """One row per job for the closing table; `metric_of(task)` names a metric to show."""
    rows = []
    for job in jobs:
        metric = metric_of(job.task)
        value = job.metrics.get(metric) if metric else None
        rows.append({"encoder": job.encoder, "task": job.task, "preset": job.preset, "seed": job.seed,
                     "status": job.status, "run id": job.run_id or "-",
                     "metric": f"{metric} = {value:.4f}" if isinstance(value, int | float) else "-",
                     "error": job.error or ""})
    return rows


def run_sweep(request: SweepRequest, home: BenchHome, echo: Callable[[str], None] = print,
              executor: Executor | None = None, listener: SweepListener | None = None) -> list[SweepJob]:
    """Validate, then run the sweep; returns every job with its status (failures do not raise)."""
    return Sweep(request, home, echo, listener).run(executor)
