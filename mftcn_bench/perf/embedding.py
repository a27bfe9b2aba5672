"""The clip-embedding figure: an episode's clips embedded sharing frames against each clip on its own and
against clips batched without sharing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mftcn_bench.perf.fixtures import cartpole_dataset, mftcn5
from mftcn_bench.perf.timing import BenchRow, Sizes, Target, alternate, one_thread, timed


def bench_embedding(sizes: Sizes, workdir: Path) -> list[BenchRow]:
    """Clips/s embedding every clip of an episode (consecutive clips share n-1 frames) with the encoder's
    `embed_episode` (one base-CNN pass per frame) against each clip on its own, and against the clips
    batched (256) without sharing frames."""

    from mftcn_bench.data.clips import clip_indices
    from mftcn_bench.encoders.base import ClipBatch

    one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    encoder = mftcn5(dataset)
    frames = dataset.load(dataset.episodes("train")[0]).frames[0, :sizes.embed_frames]
    n = len(frames)
    index = clip_indices(np.arange(n), encoder.spec.frames, encoder.spec.stride)

    def one_by_one() -> None:
        for rows in index:
            encoder.embed(ClipBatch(frames[rows][None]))

    def batched() -> None:
        for start in range(0, n, 256):
            encoder.embed(ClipBatch(frames[index[start:start + 256]]))

    rates = alternate({"ours": timed(lambda: encoder.embed_episode(frames), n), "separately": timed(one_by_one, n),
                       "batched": timed(batched, n)}, sizes.rounds)
    figure = "clip embedding, mfTCN5, clips sharing frames (96x48)"
    return [BenchRow(figure, rates["ours"], "clips/s", "naive: each clip separately", rates["separately"],
                     rates["ours"] / rates["separately"], Target(">=", 1.5)),
            BenchRow(figure, rates["ours"], "clips/s", "clips batched, frames not shared", rates["batched"],
                     rates["ours"] / rates["batched"], Target(">=", 1.5))]
