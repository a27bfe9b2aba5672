"""mfTCN5 training clips/s against a naive trainer (each clip through the network on its own; report),
and clip embedding where clips share frames (`embed_episode`) against each clip on its own and against
batched clips that share nothing (target >= 1.5x).

Run: `pytest benchmarks/bench_training.py -q -s`.
"""

from mftcn_bench.perf import bench


def test_training_ratio(record_rows, sizes, workdir):
    record_rows(bench.bench_training, sizes, workdir)


def test_embedding_ratio(record_rows, sizes, workdir):
    record_rows(bench.bench_embedding, sizes, workdir)
