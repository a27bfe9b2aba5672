"""Paper tables from stored results: our figures beside the paper's."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pandas as pd

from mftcn_bench import registry
from mftcn_bench.errors import BenchError
from mftcn_bench.specs import resolve_config
from mftcn_bench.store import ResultStore, RunRecord
from mftcn_bench.tasks.probe import TARGETS

# Table "Results on regressing Cartpole Positions and Velocities from mfTCN Embeddings" of the paper:
# (embedding size, lookback) -> Average, Position, Motion, then the five attributes in TARGETS order.
PAPER_PROBE: dict[tuple[int, int], tuple[float, ...]] = {
    (8, 1): (0.1312, 0.0201, 0.2979, 0.0238, 0.0085, 0.0279, 0.4964, 0.0993),
    (8, 2): (0.0435, 0.0017, 0.1062, 0.0011, 0.0025, 0.0016, 0.1587, 0.0537),
    (8, 4): (0.0207, 0.0014, 0.0497, 0.0008, 0.0020, 0.0014, 0.0788, 0.0207),
    (32, 1): (0.0911, 0.0052, 0.2201, 0.0045, 0.0037, 0.0072, 0.3716, 0.0686),
    (32, 2): (0.0401, 0.0019, 0.0974, 0.0014, 0.0027, 0.0015, 0.1456, 0.0492),
    (32, 4): (0.0198, 0.0013, 0.0476, 0.0008, 0.0020, 0.0013, 0.0748, 0.0203),
    (128, 1): (0.0636, 0.0040, 0.1528, 0.0030, 0.0035, 0.0056, 0.2396, 0.0661),
    (128, 2): (0.0419, 0.0018, 0.1020, 0.0011, 0.0027, 0.0015, 0.1489, 0.0552),
    (128, 4): (0.0211, 0.0014, 0.0505, 0.0007, 0.0022, 0.0014, 0.0783, 0.0227),
}
PROBE_COLUMNS = ("average", "position", "motion") + tuple(f"mse_{k}" for k in TARGETS)


def matches_current_specs(record: RunRecord) -> bool:
    """Whether a stored run used today's spec files for its encoder, task and preset, with at most the
    embedding size overridden (the paper's tables vary it). Runs of older specs or other overrides are
    not mixed into the tables."""
    try:
        encoder, task = registry.get("encoders", record.encoder), registry.get("tasks", record.task)
        _, config = resolve_config(encoder.spec, task.spec, record.preset,
                                   [("encoder.embedding_dim", record.config["encoder"]["embedding_dim"])])
    except BenchError:
        return False
    return config["encoder"] == record.config["encoder"] and config["task"] == record.config["task"]


def probe_table(store: ResultStore, preset: str | None = None) -> pd.DataFrame:
    """Rows (preset, embedding size, lookback) of mfTCN probe results of the current specs, mean over
    seeds, with the paper's figure beside each of ours ("paper" columns; empty where the paper has no
    such row)."""
    groups: dict[tuple[str, int, int], list[dict]] = defaultdict(list)
    for record in store.query(task="cartpole-probe", preset=preset):
        if record.config["encoder"]["family"] != "mftcn" or not matches_current_specs(record):
            continue
        info = record.config["encoder_info"]
        lookback = (info["frames"] - 1) * info["stride"] + 1
        groups[(record.preset, info["embedding_dim"], lookback)].append(record.metrics)
    rows = []
    for (preset_name, dim, lookback), runs in sorted(groups.items()):
        row: dict[str, object] = {"preset": preset_name, "embedding": dim, "lookback": lookback,
                                  "seeds": len(runs)}
        paper = PAPER_PROBE.get((dim, lookback))
        for i, column in enumerate(PROBE_COLUMNS):
            row[column] = float(np.mean([m[column] for m in runs]))
            row[f"{column} (paper)"] = paper[i] if paper else None
        rows.append(row)
    return pd.DataFrame(rows)
