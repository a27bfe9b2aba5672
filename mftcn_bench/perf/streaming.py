"""The streaming figure: one step of a streaming mfTCN at lookback 29 against the same at lookback 1."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mftcn_bench.perf.timing import BenchRow, Sizes, Target, alternate, one_thread, timed

STREAM_ENVS, STREAM_SHAPE = 8, (48, 96)


def _streamer(frames: int, stride: int):
    """A warmed-up streaming mfTCN (mftcn4's network, clip shape frames x stride) over 8 environments and
    the frame it is pushed each step."""

    from mftcn_bench.core.registry import get
    from mftcn_bench.core.specs import EncoderSpec
    from mftcn_bench.encoders.mftcn import MfTCNEncoder

    base = get("encoders", "mftcn4").spec
    spec = EncoderSpec(f"stream{frames}x{stride}", "mftcn", "benchmark", frames, stride, base.embedding_dim,
                       base.model, base.train)
    encoder = MfTCNEncoder(spec, image_shape=STREAM_SHAPE, seed=0)
    stream = encoder.streaming(STREAM_ENVS)
    frame = np.random.default_rng(frames).integers(0, 255, (STREAM_ENVS, *STREAM_SHAPE, 3), dtype=np.uint8)
    stream.push(frame, np.ones(STREAM_ENVS, bool))
    return stream, frame


def bench_streaming(sizes: Sizes) -> BenchRow:
    """Cost of one streaming step of 8 environments at 96x48: lookback 29 (5 frames at stride 7) against
    lookback 1."""

    one_thread()
    long_stream, long_frame = _streamer(5, 7)
    short_stream, short_frame = _streamer(1, 1)
    running = np.zeros(STREAM_ENVS, bool)
    n = sizes.stream_steps

    def push(stream, frame) -> Callable[[], None]:
        def run() -> None:
            for _ in range(n):
                stream.push(frame, running)
        return run

    rates = alternate({"29": timed(push(long_stream, long_frame), n),
                       "1": timed(push(short_stream, short_frame), n)}, sizes.stream_rounds)
    long_ms, short_ms = 1e3 / rates["29"], 1e3 / rates["1"]
    return BenchRow("streaming mfTCN step, lookback 29 (8 envs, 96x48)", long_ms, "ms", "lookback 1", short_ms,
                    long_ms / short_ms, Target("<=", 1.3, unit="x the cost"),
                    "EfficientNet-Lite0 base to block 10: one base pass per new frame whatever the lookback")
