"""Where a sweep's jobs run: a bounded local process pool, or Ray (a local instance or a cluster).

Both take a list of JobSpecs and yield (index, JobResult) as jobs finish. A job that dies with its worker
comes back as a failed JobResult, like any other failure.
"""

from __future__ import annotations

import multiprocessing
import os
import socket
import tempfile
import threading
import time
import warnings
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from typing import Protocol
from urllib.parse import urlsplit

from mftcn_bench.core.errors import BenchError
from mftcn_bench.orchestration.jobs import JobResult, JobSpec, execute, one_line

RAY_CONNECT_TIMEOUT_S = 5.0
# Ray's own defaults make an address where something answers that is not Ray slow to fail (20 GCS tries a
# second apart; Ray Client: 3 tries from 5 s with backoff). Read by Ray at import, so set before it.
RAY_QUICK_FAIL_ENV = {"RAY_NUM_REDIS_GET_RETRIES": "4", "RAY_CLIENT_INITIAL_CONNECTION_TIMEOUT_S": "2"}
RAY_DEFAULT_PORTS = {"ray": 10001, "": 6379}  # Ray Client (ray://) and the cluster's GCS address


class Executor(Protocol):
    name: str

    def map(self, specs: Sequence[JobSpec]) -> Iterator[tuple[int, JobResult]]: ...

    def close(self) -> None: ...


DRIVER_POLL_S = 1.0  # how often a local worker checks that the sweep that started it is alive


def _exit_with_driver(driver: int) -> None:
    """A local worker's initializer: end the worker once its driver is gone (killed, or its session ended), so
    no orphan goes on computing a job the driver can no longer record; the job resumes from its checkpoint
    when the sweep is started again. Polled, because a SIGKILLed driver runs no cleanup."""

    def watch() -> None:
        while os.getppid() == driver:
            time.sleep(DRIVER_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-driver", daemon=True).start()


class LocalExecutor:
    """At most `workers` jobs at once, each in its own spawned process (a fresh interpreter: no state
    inherited from the driver) that ends when the driver does. The pool starts with the first job and is
    kept for later phases."""

    name = "local"

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None

    def map(self, specs: Sequence[JobSpec]) -> Iterator[tuple[int, JobResult]]:
        if not specs:
            return
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_exit_with_driver, initargs=(os.getpid(),))
        futures: dict[Future, int] = {self._pool.submit(execute, spec): i for i, spec in enumerate(specs)}
        for future in as_completed(futures):
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001 - the worker process died (BrokenProcessPool, ...)
                result = JobResult(False, error=f"worker failed: {one_line(exc)}")
            yield futures[future], result

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


def _check_reachable(address: str) -> None:
    """A one-line error, quickly, when nothing listens at a Ray address (`ray://host:port` or
    `host:port`); `auto` and `local` are left to Ray."""
    if address in ("auto", "local"):
        return
    parts = urlsplit(address if "://" in address else f"//{address}")
    host, scheme = parts.hostname, parts.scheme
    try:
        port = parts.port or RAY_DEFAULT_PORTS.get(scheme)
    except ValueError:
        port = None
    if not host or port is None:
        raise BenchError(f"--address {address!r} is not a Ray address like ray://host:10001 or host:6379")
    try:
        with socket.create_connection((host, port), timeout=RAY_CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise BenchError(f"Ray cluster at {address} does not answer ({reason} within "
                         f"{RAY_CONNECT_TIMEOUT_S:.0f} s); check the address and that the cluster is up") from None


@contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Hide what Ray's C++ core prints to file descriptor 2 while connecting (a failure is reported as one
    line instead)."""
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


class RayExecutor:
    """Each job a Ray task needing one CPU (and one GPU when it runs on CUDA). Without an address a local
    Ray instance with `workers` CPUs is started (or the one this process already started is used); with
    one, that cluster is joined."""

    name = "ray"

    def __init__(self, workers: int, address: str | None = None) -> None:
        if address:
            for key, value in RAY_QUICK_FAIL_ENV.items():
                os.environ.setdefault(key, value)
        try:
            import ray
        except ImportError:
            raise BenchError("the ray executor needs Ray: pip install 'mftcn-bench[ray]'") from None
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            if address:
                _check_reachable(address)
            try:
                if address:
                    with _quiet_stderr(), warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        ray.init(address=address, log_to_driver=False, logging_level="WARNING")
                else:
                    ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
            except Exception as exc:  # noqa: BLE001 - ConnectionError, RuntimeError, ... as one line
                raise BenchError(f"cannot start Ray{f' at {address}' if address else ''}: {one_line(exc)}") from None
            self._started = True
        self._remote = ray.remote(num_cpus=1, max_retries=0)(execute)

    def map(self, specs: Sequence[JobSpec]) -> Iterator[tuple[int, JobResult]]:
        ray = self._ray
        # A CUDA job asks Ray for one GPU; Ray then shows the task only that GPU (as cuda:0).
        refs = {self._remote.options(num_gpus=1 if spec.device.startswith("cuda") else 0).remote(spec): i
                for i, spec in enumerate(specs)}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                try:
                    result = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - the task's worker died (WorkerCrashedError, ...)
                    result = JobResult(False, error=f"ray task failed: {one_line(exc)}")
                yield refs[ref], result

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False


def check_executor_args(kind: str, workers: int, address: str | None = None) -> None:
    """Cheap checks of the executor arguments, before any other work."""
    if kind not in ("local", "ray"):
        raise BenchError(f"unknown executor {kind!r}; valid: local, ray")
    if workers < 1:
        raise BenchError(f"--workers must be >= 1, got {workers}")
    if address and kind != "ray":
        raise BenchError("--address is for --executor ray")


def make_executor(kind: str, workers: int, address: str | None = None) -> Executor:
    check_executor_args(kind, workers, address)
    return LocalExecutor(workers) if kind == "local" else RayExecutor(workers, address)
