"""Peak RSS of the paper-scale cartpole probe (180k frames x 2 views at 160x160; target <= 4 GiB),
measured in child processes (`mftcn_bench.perf.bench_probe`).

Run: `pytest benchmarks/bench_probe_memory.py -q -s` (quick sizes measure a tenth of the fit; the
documented figure needs MFTCN_BENCH_SIZE=full, several minutes).
"""

from mftcn_bench.perf import bench


def test_probe_peak_rss(record_rows, sizes, workdir):
    record_rows(bench.bench_probe_rss, sizes, workdir)
