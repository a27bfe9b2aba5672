"""Rendering frames/s at a control task's camera and size against dm_control's default quality
(`mftcn_bench.perf.bench.bench_render`; target >= 10x).

Run: `pytest benchmarks/bench_render.py -q -s` (MFTCN_BENCH_SIZE=full for the documented sizes).
"""

import pytest

from mftcn_bench.perf import bench


@pytest.mark.parametrize("task", ["swingup", "swingup-moving"])
def test_render_ratio(record_rows, sizes, task):
    record_rows(bench.bench_render, sizes, task)
