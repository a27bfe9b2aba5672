"""The probe's memory figure: the paper-scale cartpole probe's peak RSS, from the child-process measurements
of `bench_probe`."""

from __future__ import annotations

from pathlib import Path

from mftcn_bench.perf import bench_probe
from mftcn_bench.perf.timing import BenchRow, Sizes, Target

GIB = 2**30


def bench_probe_rss(sizes: Sizes, workdir: Path) -> BenchRow:
    """Peak RSS of `cartpole-probe` (paper preset at 160x160, mftcn4) at 180,000 frames: the MLP fit measured
    at that size on features of the real shapes, the embedding phase measured on a few synthetic episodes
    plus the bytes of the features it would keep (`bench_probe`)."""
    size, full = 160, bench_probe.PAPER_TRAIN_FRAMES + bench_probe.PAPER_TEST_FRAMES
    root = bench_probe.write_dataset(workdir / "probe-datasets", max(sizes.probe_train), 1, sizes.probe_length,
                                     size)
    embedding = [bench_probe.in_child("embed", str(bench_probe.subset(root, k, 1, workdir / f"probe-{k}")))
                 for k in sizes.probe_train]
    train, test = (f * sizes.probe_fit_fraction for f in (bench_probe.PAPER_TRAIN_FRAMES,
                                                          bench_probe.PAPER_TEST_FRAMES))
    epochs = [] if sizes.probe_fit_epochs is None else [str(sizes.probe_fit_epochs)]
    fit = bench_probe.in_child("fit", str(int(train)), str(int(test)), "1000", *epochs)
    peak = bench_probe.paper_scale_peak(embedding, fit, full)
    measured = ", ".join(f"{m.frames:,} frames embedded: {m.embed_peak / GIB:.2f} GiB" for m in embedding)
    fitted = f"MLP fit on {fit.frames:,} frames: {fit.fit_peak / GIB:.2f} GiB"
    scale = "" if sizes.probe_length == 1000 and sizes.probe_fit_fraction == 1 else " (quick: not the paper's size)"
    return BenchRow(f"probe peak RSS, 180k frames x 2 views at {size}x{size}{scale}", peak / GIB, "GiB", "-", None,
                    None, Target("<=", 4, on="value", unit=" GiB"),
                    f"{measured}; {fitted}; embedding grows {bench_probe.embedding_growth(embedding) / 1024:.2f} KiB "
                    f"per frame")
