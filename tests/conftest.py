"""Shared fixtures: a private harness home per test."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture
def home(tmp_path, monkeypatch):
    from mftcn_bench.home import BenchHome

    monkeypatch.setenv("MFTCN_BENCH_HOME", str(tmp_path / "home"))
    return BenchHome.resolve()
