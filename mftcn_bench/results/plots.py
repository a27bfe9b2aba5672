"""Plots (PNG, via `figure`) from stored results: learning curves per task, probe MSE vs
lookback, pouring error vs lookback.

Seeds are aggregated as in the tables: mean, and a band or error bar of one sample std (ddof=1), over the runs a
table counts, at the presets tables show (paper, quick). Learning
curves are interpolated onto a common frames grid that every seed covers (up to the shortest run).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from mftcn_bench.results.figure import plt, save_figure
from mftcn_bench.results.paper_tables import POURING, PROBE
from mftcn_bench.results.selection import (
    TABLE_PRESETS,
    Accept,
    counted_runs,
    matches_current_specs,
    variant_key,
    variant_label,
)
from mftcn_bench.results.stats import seed_stats
from mftcn_bench.results.store import RunRecord

CURVE = "train"
GRID_POINTS = 200
PROBE_METRICS = ("average", "position", "motion")
POURING_METRICS = ("static_error", "motion_error", "alignment_error")


def lookback(record: RunRecord) -> int | None:
    """Frames spanned by the run's clips, from its encoder config."""
    encoder = record.config.get("encoder", {})
    try:
        return (int(encoder["frames"]) - 1) * int(encoder["stride"]) + 1
    except (KeyError, TypeError, ValueError):
        return None


def mean_curve(curves: Sequence[dict[str, list[float]]], x: str = "frames",
               y: str = "return") -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(grid, mean, std or None for one seed) of several runs' curves on a common grid from the largest
    first x to the smallest last x, so that no seed is extrapolated."""
    usable = [c for c in curves if len(c.get(x, [])) >= 1 and len(c.get(x, [])) == len(c.get(y, []))]
    if not usable:
        raise ValueError("no usable curve")
    start = max(float(c[x][0]) for c in usable)
    stop = min(float(c[x][-1]) for c in usable)
    grid = np.linspace(start, stop, GRID_POINTS) if stop > start else np.array([stop])
    values = np.stack([np.interp(grid, np.asarray(c[x], float), np.asarray(c[y], float)) for c in usable])
    std = values.std(axis=0, ddof=1) if len(usable) >= 2 else None
    return grid, values.mean(axis=0), std


def _table_runs(records: Iterable[RunRecord], accept: Accept) -> list[RunRecord]:
    """The runs a table counts, of the presets tables show (`TABLE_PRESETS`: not the smoke or demo data)."""
    return [r for r in counted_runs(records, accept) if r.preset in TABLE_PRESETS]


def _group(runs: Iterable[RunRecord]) -> dict[tuple, list[RunRecord]]:
    groups: dict[tuple, list[RunRecord]] = defaultdict(list)
    for record in runs:
        groups[(record.task, record.preset)].append(record)
    return dict(sorted(groups.items()))


def plot_curves(records: Iterable[RunRecord], out: Path, task: str | None = None,
                accept: Accept = matches_current_specs) -> list[Path]:
    """`curves-<task>-<preset>.png`: training return vs env frames, one line per encoder, mean over seeds
    with a ±1 std band."""
    runs = [r for r in _table_runs(records, accept) if CURVE in r.curves and (task is None or r.task == task)]
    written = []
    for (task_name, preset), group in _group(runs).items():
        fig, ax = plt.subplots(figsize=(7, 4.5))
        by_variant: dict[tuple, list[RunRecord]] = defaultdict(list)
        for record in group:
            by_variant[variant_key(record)].append(record)
        for variant in sorted(by_variant, key=str):
            members = by_variant[variant]
            try:
                grid, mean, std = mean_curve([r.curves[CURVE] for r in members])
            except ValueError:
                continue
            line, = ax.plot(grid, mean, label=f"{variant_label(members[0])} (n={len(members)})")
            if std is not None:
                ax.fill_between(grid, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        ax.set(xlabel="environment frames", ylabel="episode return (training)",
               title=f"{task_name}, preset {preset}: mean over seeds, band ±1 sample std")
        ax.legend(fontsize="small")
        written.append(save_figure(fig, out / f"curves-{task_name}-{preset}.png"))
    return written


def _lookback_plot(runs: Sequence[RunRecord], metrics: Sequence[str], ylabel: str, title: str,
                   path: Path, reference: dict[tuple[str, int | None], dict[int, float]] | None = None,
                   log: bool = False) -> Path:
    """One panel per metric, one line per embedding size in it (one colour per size across the panels):
    mean over seeds vs lookback, error bars ±1 std; dashed in the same colour, `reference[(metric, embedding
    size)]` ({lookback: value}) of a plotted size, or `reference[(metric, None)]` for any size."""
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.6 * len(metrics) + 1.4, 3.8), sharex=True, squeeze=False)
    by_dim: dict[object, list[RunRecord]] = defaultdict(list)
    for record in runs:
        by_dim[record.config.get("encoder", {}).get("embedding_dim")].append(record)
    colours = {dim: f"C{i}" for i, dim in enumerate(sorted(by_dim, key=str))}
    for ax, metric in zip(axes[0], metrics, strict=True):
        for dim in sorted(by_dim, key=str):
            points: dict[int, list[RunRecord]] = defaultdict(list)
            for record in by_dim[dim]:
                points[lookback(record)].append(record)
            xs, means, errs = [], [], []
            for x in sorted(points):
                s = seed_stats(r.metrics.get(metric) for r in points[x])
                if s is not None:
                    xs.append(x)
                    means.append(s.mean)
                    errs.append(s.std or 0.0)
            if not xs:
                continue
            label = f"embedding {dim}" if len(by_dim) > 1 else "ours"
            ax.errorbar(xs, means, yerr=errs, marker="o", capsize=3, color=colours[dim], label=label)
            paper = (reference or {}).get((metric, dim)) or (reference or {}).get((metric, None))
            if paper:
                ax.plot(sorted(paper), [paper[k] for k in sorted(paper)], linestyle="--", marker="x",
                        color=colours[dim], label=f"{label}, paper" if len(by_dim) > 1 else "paper")
        if log:
            ax.set_yscale("log")
        ax.set(xlabel="lookback (frames)", title=metric)
    axes[0][0].set_ylabel(ylabel)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="center right", fontsize="small")
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1 - 1.4 / (3.6 * len(metrics) + 1.4), 1))
    return save_figure(fig, path)


def _paper_probe_reference() -> dict[tuple[str, int | None], dict[int, float]]:
    """The paper's probe figures: (metric, embedding size) -> {lookback: MSE}."""
    columns = [c.metric for c in PROBE.columns]
    out: dict[tuple[str, int | None], dict[int, float]] = defaultdict(dict)
    for row in PROBE.rows:
        if row.paper is None:  # a row of ours only (the from-scratch ablation)
            continue
        dim, look = row.labels
        for i, metric in enumerate(columns):
            out[(metric, int(dim))][int(look)] = row.paper[i]
    return dict(out)


def _paper_pouring_reference() -> dict[tuple[str, int | None], dict[int, float]]:
    """The paper's mfTCN pouring errors (on the real data set, ours on the simulated one): (metric, None) ->
    {lookback: %}."""
    columns = [c.metric for c in POURING.columns]
    out: dict[tuple[str, int | None], dict[int, float]] = defaultdict(dict)
    for row in POURING.rows:
        if row.labels[0].startswith("mfTCN") and row.paper is not None:
            for i, metric in enumerate(columns):
                if row.paper[i] is not None:
                    out[(metric, None)][int(row.labels[1])] = row.paper[i]
    return dict(out)


def plot_probe_lookback(records: Iterable[RunRecord], out: Path, accept: Accept = matches_current_specs,
                        metrics: Sequence[str] = PROBE_METRICS) -> list[Path]:
    """`probe-lookback-<preset>.png`: cartpole-probe MSE of the mfTCN encoders vs lookback."""
    runs = [r for r in _table_runs(records, accept)
            if r.task == "cartpole-probe" and r.config.get("encoder", {}).get("family") == "mftcn"]
    return [_lookback_plot(group, metrics, "test MSE (log scale)",
                           f"cartpole-probe, preset {preset}: mfTCN MSE vs lookback (dashed: paper)",
                           out / f"probe-lookback-{preset}.png", _paper_probe_reference(), log=True)
            for (_, preset), group in _group(runs).items()]


def plot_pouring_lookback(records: Iterable[RunRecord], out: Path, accept: Accept = matches_current_specs,
                          metrics: Sequence[str] = POURING_METRICS) -> list[Path]:
    """`pouring-lookback-<preset>.png`: pouring errors (%) of the mfTCN encoders vs lookback."""
    runs = [r for r in _table_runs(records, accept)
            if r.task == "pouring" and r.config.get("encoder", {}).get("family") == "mftcn"]
    return [_lookback_plot(group, metrics, "error (%)",
                           f"pouring, preset {preset}: mfTCN error vs lookback (dashed: paper, on the real data)",
                           out / f"pouring-lookback-{preset}.png", _paper_pouring_reference())
            for (_, preset), group in _group(runs).items()]
