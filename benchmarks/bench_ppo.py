"""PPO collection frames/s (torchrl Collector, untrained PPO policy) on mfTCN5 embeddings against true
state (target >= 0.5), and on true state against torchrl's SerialEnv of DMControlEnv (target >= 2x); the PPO
update on pixels-cnn clips against each head running the trunk (target >= 2x).

Run: `pytest benchmarks/bench_ppo.py -q -s`.
"""

from mftcn_bench.perf import bench


def test_ppo_pixels_ratio(record_rows, sizes):
    record_rows(bench.bench_ppo_pixels, sizes)


def test_ppo_pixels_160_ratio(record_rows, sizes):
    record_rows(bench.bench_ppo_pixels_160, sizes)


def test_ppo_state_ratio(record_rows, sizes):
    record_rows(bench.bench_ppo_state, sizes)


def test_ppo_update_pixels_ratio(record_rows, sizes):
    record_rows(bench.bench_ppo_update_pixels, sizes)
