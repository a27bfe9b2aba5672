"""Synthetic RunRecords for tests of reports, leaderboards, export and plots (nothing is run)."""

from __future__ import annotations

from mftcn_bench.core import registry
from mftcn_bench.core.provenance import content_hash
from mftcn_bench.core.specs import resolve_config
from mftcn_bench.results.store import RunRecord


def probe_config(encoder: str, preset: str = "quick", embedding_dim: int | None = None) -> dict:
    """The resolved config a real cartpole-probe run of `encoder` would store."""
    overrides = [("encoder.embedding_dim", embedding_dim)] if embedding_dim else []
    _, config = resolve_config(registry.get("encoders", encoder).spec, registry.get("tasks", "cartpole-probe").spec,
                               preset, overrides)
    return config


def make_record(encoder: str, task: str, seed: int, metrics: dict, *, preset: str = "quick",
                config: dict | None = None, created_at: str = "2026-01-02T03:04:05+00:00",
                curves: dict | None = None, frames: int = 1, stride: int = 1, embedding_dim: int = 32,
                family: str = "mftcn") -> RunRecord:
    config = config or {"encoder": {"name": encoder, "family": family, "frames": frames, "stride": stride,
                                    "embedding_dim": embedding_dim, "model": {}, "train": {}},
                        "task": {"name": task}}
    run_id = content_hash({"e": encoder, "t": task, "s": seed, "p": preset, "c": config, "at": created_at})
    return RunRecord(run_id, encoder, task, preset, seed, "dataset", config,
                     {"mftcn-bench": "0.1.0", "torch": "2.13.0"}, metrics, {"total_s": 1.0}, None, created_at,
                     curves or {})
