"""Shared fixtures: a private harness home per test."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")


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
