"""Per-step cost of embedding 8 environments' newest clips at 96x48: streaming (one base-CNN pass per new
frame, per-frame features kept in a ring buffer) against re-embedding every whole clip each step.

Run: `pytest benchmarks/bench_streaming.py --benchmark-only -q` (the model is mftcn4's [model] table,
embedding 32; the clip shapes are those of mftcn1, mftcn5, mftcn13 and mftcn29).
"""

from __future__ import annotations

import numpy as np
import pytest

from mftcn_bench.core.registry import get
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.encoders.base import ClipBatch
from mftcn_bench.encoders.mftcn import MfTCNEncoder

ENVS = 8
SHAPE = (48, 96)  # height, width
CLIPS = {1: (1, 1), 5: (5, 1), 13: (4, 4), 29: (5, 7)}  # lookback: (frames, stride)
WARMUP = 5  # untimed calls first (kernel set-up, allocator), the same for both ways


def encoder(lookback: int) -> MfTCNEncoder:
    base = get("encoders", "mftcn4").spec
    frames, stride = CLIPS[lookback]
    spec = EncoderSpec(f"mftcn{lookback}", "mftcn", "benchmark", frames, stride, 32, base.model, base.train)
    return MfTCNEncoder(spec, image_shape=SHAPE, seed=0)


def history(lookback: int) -> np.ndarray:
    """uint8 [ENVS, lookback, H, W, 3] of past frames per environment."""
    return np.random.default_rng(lookback).integers(0, 255, (ENVS, lookback, *SHAPE, 3), dtype=np.uint8)


@pytest.mark.parametrize("lookback", sorted(CLIPS))
def test_streaming(benchmark, lookback):
    enc, frames = encoder(lookback), history(lookback)
    stream = enc.streaming(ENVS)
    stream.push(frames[:, 0], np.ones(ENVS, bool))
    for t in range(1, lookback):
        stream.push(frames[:, t], np.zeros(ENVS, bool))
    newest, running = frames[:, -1], np.zeros(ENVS, bool)
    for _ in range(WARMUP):
        stream.push(newest, running)
    benchmark.group = f"lookback {lookback:2d}"
    out = benchmark(stream.push, newest, running)
    assert out.shape == (ENVS, 32)


@pytest.mark.parametrize("lookback", sorted(CLIPS))
def test_reembed(benchmark, lookback):
    enc, frames = encoder(lookback), history(lookback)
    frames_n, stride = CLIPS[lookback]
    index = clip_indices(np.array([lookback - 1]), frames_n, stride)[0]
    clips = ClipBatch(np.ascontiguousarray(frames[:, index]))  # [ENVS, n, H, W, 3]
    for _ in range(WARMUP):
        enc.embed(clips)
    benchmark.group = f"lookback {lookback:2d}"
    out = benchmark(enc.embed, clips)
    assert out.shape == (ENVS, 32)


def test_streaming_cost_ratio(record_rows, sizes):
    """Lookback 29 against lookback 1, alternated in one run (`mftcn_bench.perf.bench.bench_streaming`; target
    <= 1.5x the cost)."""
    from mftcn_bench.perf import bench

    record_rows(bench.bench_streaming, sizes)
