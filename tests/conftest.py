"""Shared fixtures: a private harness home per test."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
if "PYTEST_XDIST_WORKER" in os.environ:
    # One worker per core (pyproject's addopts): one math thread each, or two workers' torch and BLAS
    # pools oversubscribe the cores (measured on 2 cores: 611 s for the suite with the default threads).
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(variable, "1")


@pytest.fixture
def home(tmp_path, monkeypatch):
    from mftcn_bench.core.home import BenchHome

    monkeypatch.setenv("MFTCN_BENCH_HOME", str(tmp_path / "home"))
    return BenchHome.resolve()


@pytest.fixture
def one_torch_thread():
    """torch on one thread for this test only (bitwise-reproducible sums), restored afterwards so later
    tests do not depend on the order they run in."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
