"""What a sweep's worker does: build one dataset, fit one encoder, or run one (encoder, task, seed).

These functions run in a worker process (a local process pool or a Ray worker) and take and return plain
picklable data. A job never raises: a failure comes back as a JobResult with a one-line error, so one
failed job never stops a sweep. Each job limits its numeric libraries to `threads` threads, the same
whatever the executor, so the results do not depend on where a job ran.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

from mftcn_bench.core.allocator import keep_freed_memory
from mftcn_bench.results.store import RunRecord

JobKind = Literal["dataset", "encoder", "run"]


@dataclass(frozen=True)
class JobSpec:
    """One unit of work. `home` is the worker's harness home (None: the worker's own default, for
    cluster workers that do not share the driver's disk)."""

    kind: JobKind
    encoder: str
    task: str
    preset: str | None
    seed: int
    overrides: Sequence[tuple[str, Any]]
    home: str | None
    threads: int = 1
    device: str = "cpu"           # what the job's RunRequest asks for (`Sweep._job_device`)
    deterministic: bool = False


@dataclass(frozen=True)
class JobResult:
    ok: bool
    fingerprint: str | None = None
    record: RunRecord | None = None
    reused: bool = False
    error: str | None = None
    seconds: float = 0.0


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or "(no message)"
    return f"{type(exc).__name__}: {text}"


def _work(spec: JobSpec) -> JobResult:
    from mftcn_bench.core.home import BenchHome
    from mftcn_bench.run.artifacts import build_encoder, prepare_dataset
    from mftcn_bench.run.plan import RunRequest, prepare_with_encoder
    from mftcn_bench.run.runner import run

    home = BenchHome.resolve(spec.home)
    request = RunRequest(spec.encoder, spec.task, spec.preset, spec.seed, tuple(spec.overrides),
                         device=spec.device, deterministic=spec.deterministic)
    if spec.kind == "run":
        outcome = run(request, home, show_progress=False)
        return JobResult(True, fingerprint=outcome.record.dataset_id, record=outcome.record, reused=outcome.reused)
    prepared, untrained = prepare_with_encoder(request)
    dataset = prepare_dataset(prepared, home, show_progress=False)
    if spec.kind == "encoder":
        _, fit = build_encoder(prepared, dataset, home, show_progress=False, untrained=untrained)
        return JobResult(True, fingerprint=dataset.fingerprint, reused=bool(fit.get("reused")))
    return JobResult(True, fingerprint=dataset.fingerprint)


def execute(spec: JobSpec) -> JobResult:
    """Do the job in this process with `spec.threads` threads for torch and BLAS."""
    import torch
    from threadpoolctl import threadpool_limits

    began = time.monotonic()
    keep_freed_memory()  # a spawned worker starts with glibc's defaults
    torch.set_num_threads(spec.threads)
    try:
        with threadpool_limits(limits=spec.threads):
            result = _work(spec)
    except Exception as exc:  # noqa: BLE001 - reported as this job's failure, the sweep goes on
        return JobResult(False, error=one_line(exc), seconds=time.monotonic() - began)
    return JobResult(result.ok, result.fingerprint, result.record, result.reused, None, time.monotonic() - began)
