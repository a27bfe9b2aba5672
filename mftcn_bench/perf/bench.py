"""`mftcn-bench bench`: the harness's speed, each figure a ratio against a reference measured in the same run.

Absolute times drift on a shared machine, so every figure is measured beside its reference, in the same
process, alternating blocks of the two (the order reversed every other round) so that a change of load
hits both. Everything runs with one torch thread (`torch.set_num_threads(1)`; the probe's child process also
with OMP/MKL/OpenBLAS at 1 thread), so a ratio is not an artefact of thread counts. The targets:

| figure | reference | target |
|---|---|---|
| rendering frames/s at a task's camera and size | dm_control's defaults (2048 shadow map, 4x MSAA) | >= 10x |
| streaming mfTCN step on the pretrained base, lookback 29 | streaming, lookback 1 | <= 1.3x the cost |
| PPO collection frames/s on mfTCN5 embeddings (96x48), each stream | the same loop rendering only | >= 0.7x |
| PPO collection frames/s on mfTCN5 embeddings (96x48), agent rate | the physics-rate stream; true state | report |
| PPO collection frames/s on mfTCN5 embeddings (160x160, input x0.6) | rendering only; full scale | >= 0.7x; report |
| PPO collection frames/s on true state | torchrl SerialEnv of 8 DMControlEnv | >= 2x |
| PPO update minibatches/s on pixels-cnn clips (cheetah) | each head running the trunk, default layout | >= 2x |
| encoder training clips/s, mfTCN5 | each clip through the network on its own | report |
| feature-cache build frames/s (EfficientNet-Lite0 to block 10) | the raw base forward on the same frames | >= 0.8x |
| the frozen base's forward frames/s on the specs' engine (96x48, 160x160) | eager PyTorch | report |
| head training steps/s on the cache, mfTCN5 | end-to-end small-cnn mfTCN5 steps/s | report |
| clip embedding where clips share frames | each clip on its own; clips batched but not sharing | >= 1.5x |
| dataset read frames/s | the trainer's consumption of frames | >= 2x |
| peak RSS of the paper-scale probe | - | <= 4 GiB |

The machinery (targets, rows, alternation, the table) is in `timing`, the data and encoders the figures
share in `fixtures`, and each family of figures in its own module, a function per figure returning
`BenchRow`s: `rendering`, `streaming`, `collection` (PPO), `ppo_update`, `training`, `frozen_base`, `embedding`,
`probe_memory` and `bench_device`. This module names the figures and runs them (`run_bench`); the command
is `mftcn_bench.cli.bench_command`.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from mftcn_bench.perf.bench_device import bench_device
from mftcn_bench.perf.collection import bench_ppo_pixels, bench_ppo_pixels_160, bench_ppo_state
from mftcn_bench.perf.embedding import bench_embedding
from mftcn_bench.perf.frozen_base import bench_base_engine, bench_feature_cache
from mftcn_bench.perf.ppo_update import bench_ppo_update_pixels
from mftcn_bench.perf.probe_memory import bench_probe_rss
from mftcn_bench.perf.rendering import bench_render
from mftcn_bench.perf.streaming import bench_streaming
from mftcn_bench.perf.timing import FULL, QUICK, BenchRow, Sizes, format_table
from mftcn_bench.perf.training import bench_dataset_read, bench_head_training, bench_training

# benchmarks/ reaches the figures, the sizes and the table through this module (`bench.bench_render`,
# `bench.QUICK`, `bench.format_table`), as it did when they all lived here.
__all__ = ["FIGURES", "FULL", "ON_DEVICE_ONLY", "QUICK", "BenchRow", "Sizes", "bench_base_engine", "bench_dataset_read",
           "bench_device", "bench_embedding", "bench_feature_cache", "bench_head_training", "bench_ppo_pixels",
           "bench_ppo_pixels_160",
           "bench_ppo_state", "bench_ppo_update_pixels", "bench_probe_rss", "bench_render", "bench_streaming",
           "bench_training", "format_table", "run_bench"]

FIGURES = ("render", "streaming", "ppo-pixels", "ppo-pixels-160", "ppo-state", "ppo-update", "training",
           "feature-cache", "base-engine", "head-training", "embedding", "dataset", "probe-rss", "device")
# Run by default only on a GPU (`--device` resolving to CUDA); on the CPU `--only device` checks the path.
ON_DEVICE_ONLY = ("device",)


def run_bench(sizes: Sizes, only: Sequence[str] = FIGURES, workdir: Path | None = None,
              progress: Callable[[str], None] | None = None, placement=None) -> list[BenchRow]:
    """The figures named in `only`, in FIGURES order; data goes to `workdir` (a temporary folder if None);
    "device" compares `placement`'s device (default: the CPU) with the CPU."""
    from mftcn_bench.core.device import CPU

    unknown = sorted(set(only) - set(FIGURES))
    if unknown:
        from mftcn_bench.core.errors import SpecError

        raise SpecError(f"unknown benchmark(s) {unknown}; choose from {', '.join(FIGURES)}")
    with tempfile.TemporaryDirectory(prefix="mftcn-bench-") as tmp:
        work = Path(workdir) if workdir is not None else Path(tmp)
        steps: dict[str, Callable[[], BenchRow | list[BenchRow]]] = {
            "render": lambda: [bench_render(sizes, "swingup"), bench_render(sizes, "swingup-moving")],
            "streaming": lambda: bench_streaming(sizes),
            "ppo-pixels": lambda: bench_ppo_pixels(sizes),
            "ppo-pixels-160": lambda: bench_ppo_pixels_160(sizes),
            "ppo-state": lambda: bench_ppo_state(sizes),
            "ppo-update": lambda: bench_ppo_update_pixels(sizes),
            "training": lambda: bench_training(sizes, work),
            "feature-cache": lambda: bench_feature_cache(sizes, work),
            "base-engine": lambda: bench_base_engine(sizes),
            "head-training": lambda: bench_head_training(sizes, work),
            "embedding": lambda: bench_embedding(sizes, work),
            "dataset": lambda: bench_dataset_read(sizes, work),
            "probe-rss": lambda: bench_probe_rss(sizes, work),
            "device": lambda: bench_device(sizes, work, placement or CPU),
        }
        rows: list[BenchRow] = []
        for name in FIGURES:
            if name in only:
                began = time.monotonic()
                out = steps[name]()
                rows.extend(out if isinstance(out, list) else [out])
                if progress is not None:
                    progress(f"{name}: {time.monotonic() - began:.0f} s")
        return rows
