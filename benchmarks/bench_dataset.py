"""Dataset read frames/s (chunks decoded, checksums checked, no cache) against the frames/s the mfTCN5
trainer consumes (target >= 2x).

Run: `pytest benchmarks/bench_dataset.py -q -s`.
"""

from mftcn_bench.perf import bench


def test_dataset_read_ratio(record_rows, sizes, workdir):
    record_rows(bench.bench_dataset_read, sizes, workdir)
