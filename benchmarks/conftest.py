"""Benchmark settings and helpers: one torch thread, so figures are comparable on a shared 2-core machine;
`record_rows` runs one of `mftcn_bench.perf.bench`'s figures and records its ratio (never fails on speed).

Sizes: `QUICK` (CI) unless MFTCN_BENCH_SIZE=full.
"""

from __future__ import annotations

import math
import os

import pytest
import torch

from mftcn_bench.perf import bench


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config: pytest.Config) -> None:
    """Serial, whatever `addopts` says: the test suite runs one xdist worker per core, and a figure
    timed beside another worker would measure the contention (pytest-benchmark turns itself off)."""
    config.option.numprocesses = 0
    config.option.dist = "no"


@pytest.fixture(autouse=True, scope="session")
def one_thread():
    from mftcn_bench.sim.rendering import ensure_gl

    ensure_gl()  # MUJOCO_GL=egl unless set, before anything imports dm_control
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def sizes() -> bench.Sizes:
    return bench.FULL if os.environ.get("MFTCN_BENCH_SIZE") == "full" else bench.QUICK


@pytest.fixture(scope="session")
def workdir(tmp_path_factory):
    """One folder per session, so the rendered cartpole dataset is collected once for every figure."""
    return tmp_path_factory.mktemp("bench")


@pytest.fixture
def record_rows(benchmark):
    """`record_rows(fn, *args)`: runs `fn(*args)` once under pytest-benchmark (its time is the figure's
    wall time), stores each row's figure, reference, ratio, target and met in `extra_info`, prints the
    table, and fails only if a figure is not a positive finite number (an error, never a speed)."""

    def run(fn, *args):
        out = benchmark.pedantic(fn, args=args, rounds=1, iterations=1)
        rows = out if isinstance(out, list) else [out]
        for i, row in enumerate(rows):
            benchmark.extra_info[f"row{i}"] = {**row.cells(), "value_number": row.value,
                                               "reference_number": row.reference_value}
        print("\n" + bench.format_table(rows))
        for row in rows:
            assert math.isfinite(row.value) and row.value > 0, row
            assert row.ratio is None or (math.isfinite(row.ratio) and row.ratio > 0), row
        return rows

    return run
