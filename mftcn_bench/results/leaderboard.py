"""Leaderboards: one markdown file per task (a board per preset) and an index, written from the store.

A pure function of the stored results: the date shown is the latest `created_at` of the runs behind an
entry, never today's date, and every ordering is fixed, so the same results give the same bytes. The
metric and its direction come from the task spec's `[leaderboard]` table; tasks without one (or not
installed here) get no board and are named in the index.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from tabulate import tabulate

from mftcn_bench.core import registry
from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.results.selection import (
    Accept,
    code_label,
    counted_runs,
    left_out_line,
    matches_current_specs,
    preset_order,
    variant_key,
    variant_label,
)
from mftcn_bench.results.stats import IQM_MIN_SEEDS, STD_KIND, SeedStats, format_iqm, format_mean_std, seed_stats
from mftcn_bench.results.store import RunRecord


@dataclass(frozen=True)
class Ranking:
    """How a task's results are ranked: the metric, its direction and its printed name."""

    metric: str
    higher_is_better: bool
    label: str


@dataclass(frozen=True)
class Entry:
    """One leaderboard line: an encoder variant's statistics over seeds on one (task, preset)."""

    encoder: str
    stats: SeedStats
    preset: str
    version: str
    date: str


def ranking(task: str) -> Ranking | None:
    """The task spec's `[leaderboard]` table, or None when it has none or the task is not installed."""
    try:
        table = dict(registry.get("tasks", task).spec.leaderboard)
    except BenchError:
        return None
    if not table:
        return None
    metric = table.get("metric")
    if not isinstance(metric, str) or not isinstance(table.get("higher_is_better"), bool):
        raise SpecError(f"task spec {task!r}: [leaderboard] needs metric = \"<name>\" and "
                        f"higher_is_better = true/false")
    return Ranking(metric, table["higher_is_better"], str(table.get("label", metric)))


def entries(runs: Sequence[RunRecord], rank: Ranking) -> list[Entry]:
    """Entries of one (task, preset), best first; ties (and missing metrics) ordered by encoder name."""
    groups: dict[tuple, list[RunRecord]] = defaultdict(list)
    for record in runs:
        groups[variant_key(record)].append(record)
    out = []
    for group in groups.values():
        stats = seed_stats(r.metrics.get(rank.metric) for r in group)
        if stats is None:
            continue
        version = ", ".join(sorted({code_label(r) for r in group}))
        date = max(r.created_at for r in group)[:10]
        out.append(Entry(variant_label(group[0]), stats, group[0].preset, version, date))
    sign = -1.0 if rank.higher_is_better else 1.0
    return sorted(out, key=lambda e: (sign * e.stats.mean, e.encoder))


def _board(rank: Ranking, board: Sequence[Entry]) -> str:
    headers = ["rank", "encoder", f"{rank.label} (mean ± std)", "IQM [95% CI]", "seeds", "preset",
               "encoder code", "date"]
    rows = [[str(i), e.encoder, format_mean_std(e.stats), format_iqm(e.stats), str(e.stats.n), e.preset,
             e.version, e.date] for i, e in enumerate(board, 1)]
    return tabulate(rows, headers=headers, tablefmt="github", disable_numparse=True)


def _by_task_and_preset(runs: Iterable[RunRecord]) -> dict[str, dict[str, list[RunRecord]]]:
    out: dict[str, dict[str, list[RunRecord]]] = defaultdict(lambda: defaultdict(list))
    for record in runs:
        out[record.task][record.preset].append(record)
    return {task: dict(sorted(presets.items(), key=lambda item: preset_order(item[0])))
            for task, presets in sorted(out.items())}


def _explain(rank: Ranking) -> str:
    better = "higher" if rank.higher_is_better else "lower"
    return (f"Ranked by {rank.label} (metric `{rank.metric}`, {better} is better). std: {STD_KIND}; "
            f"IQM: interquartile mean (the mean after cutting floor(n/4) of the n seeds from each end, so "
            f"with fewer than 4 seeds nothing is cut and it is the mean) with a percentile-bootstrap 95% "
            f"interval, given from {IQM_MIN_SEEDS} seeds on. Only runs of the current spec files count (an "
            f"overridden embedding size is its own entry); of repeated runs of one seed the latest counts. "
            f"Encoder code: the distribution and version that shipped the encoder (a plugin's own). Date: the "
            f"latest of the entry's runs.")


_INDEX_TITLE = "# Leaderboards"


def render_boards(records: Iterable[RunRecord], accept: Accept = matches_current_specs) -> dict[str, str]:
    """File name -> markdown text: `<task>.md` for each task with a ranking, and `README.md`."""
    records = list(records)
    files: dict[str, str] = {}
    index = [_INDEX_TITLE, "",
             "Generated by `mftcn-bench leaderboard` from the results store; do not edit by hand. Results "
             "travel between machines as JSON files (`mftcn-bench results export DIR` / `results import DIR`).",
             "",
             "| task | ranked by | preset | best | seeds |", "|---|---|---|---|---|"]
    unranked = []
    for task, presets in _by_task_and_preset(counted_runs(records, accept)).items():
        rank = ranking(task)
        if rank is None:
            unranked.append(task)
            continue
        direction = "higher" if rank.higher_is_better else "lower"
        lines = [f"# {task}", "", _explain(rank)]
        for preset, runs in presets.items():
            board = entries(runs, rank)
            lines += ["", f"## preset `{preset}`", "", _board(rank, board)]
            best = board[0] if board else None
            index.append(f"| [{task}]({task}.md) | {rank.label} ({direction} is better) | {preset} | "
                         + (f"{best.encoder}: {format_mean_std(best.stats)} | {best.stats.n} |" if best
                            else "- | - |"))
        files[f"{task}.md"] = "\n".join(lines) + "\n"
    if unranked:
        index += ["", "Stored results without a board (the task is not installed here or its spec has no "
                  "`[leaderboard]` table): " + ", ".join(unranked) + "."]
    skipped = left_out_line(records, accept)
    if skipped:
        index += ["", skipped]
    files["README.md"] = "\n".join(index) + "\n"
    return files


def write_boards(records: Iterable[RunRecord], out: Path, accept: Accept = matches_current_specs) -> list[Path]:
    """Write the boards under `out` (atomic per file); returns the paths written. In a folder that this
    function wrote before (its README.md is the index), a board of a task that no longer has one is
    removed, so that a renamed task or a withdrawn record leaves no stale board behind."""
    out.mkdir(parents=True, exist_ok=True)
    boards = render_boards(records, accept)
    index = out / "README.md"
    if index.is_file() and index.read_text(encoding="utf-8").startswith(_INDEX_TITLE):
        for stale in sorted(set(out.glob("*.md")) - {out / name for name in boards}):
            stale.unlink()
    written = []
    for name, text in boards.items():
        atomic_write_bytes(out / name, text.encode())
        written.append(out / name)
    return written
