"""Leaderboards: one markdown file per task (a board per preset) and an index, written from the store.

A pure function of the stored results: the date shown is the latest `created_at` of the runs behind an
entry, never today's date, and every ordering is fixed, so the same results give the same bytes. The
metric, its direction and its printing come from the task spec's `[leaderboard]` table; tasks without one
(or not installed here) get no board and are named in the index. Pixel encoders are ranked; references (an
encoder that reads the true state, the scorecard's floor and ceiling: `results.references`) are listed apart
below them. The index opens with the overall board, the scorecard's (`results.scorecard`).

An entry's runs share one data set (`results.selection`), but entries of one board can rest on different
recordings of the task's data (another machine, another collector's code): each entry shows its data set's
fingerprint, and one not on the board's (the one most of its runs read) is marked.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from tabulate import tabulate

from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.results import scorecard
from mftcn_bench.results.ranking import Ranking, ranking
from mftcn_bench.results.references import privileged_of, reference_role
from mftcn_bench.results.selection import (
    TABLE_PRESETS,
    Accept,
    code_label,
    counted_runs,
    left_out_line,
    matches_current_specs,
    other_dataset_note,
    preset_order,
    shared_dataset,
    variant_key,
    variant_label,
)
from mftcn_bench.results.stats import IQM_MIN_SEEDS, STD_KIND, SeedStats, seed_stats
from mftcn_bench.results.store import RunRecord


@dataclass(frozen=True)
class Entry:
    """One leaderboard line: an encoder variant's statistics over seeds on one (task, preset)."""

    encoder: str
    stats: SeedStats
    preset: str
    version: str
    date: str
    reference: str | None = None    # why it is listed apart (`references.reference_role`); None: ranked
    privileged: tuple[str, ...] = ()  # what its encoder declared besides pixels
    run_ids: tuple[str, ...] = ()   # the runs behind it, by seed
    dataset: str | None = None      # the fingerprint of the data set its runs read; None: it reads none
    other_dataset: bool = False     # it reads a data set other than the board's (`selection.shared_dataset`)

    @property
    def reads(self) -> str:
        """A ranked encoder's inputs: pixels, and what it declared besides."""
        return ", ".join(("pixels", *self.privileged))


def entries(runs: Sequence[RunRecord], rank: Ranking) -> list[Entry]:
    """Entries of one (task, preset), best first; ties (and missing metrics) ordered by encoder name."""
    shared = shared_dataset(runs)
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
        dataset = group[0].dataset_id or None
        out.append(Entry(variant_label(group[0]), stats, group[0].preset, version, date, reference_role(group[0]),
                         privileged_of(group[0]), tuple(r.run_id for r in sorted(group, key=lambda r: r.seed)),
                         dataset, dataset is not None and dataset != shared))
    sign = -1.0 if rank.higher_is_better else 1.0
    return sorted(out, key=lambda e: (sign * e.stats.mean, e.encoder))


def dataset_label(entry: Entry) -> str:
    """The entry's data set fingerprint, `*` after one not on the board's; `-` for an encoder that reads none."""
    return "-" if entry.dataset is None else entry.dataset + (" *" if entry.other_dataset else "")


def _board(rank: Ranking, board: Sequence[Entry], shared: str | None) -> str:
    """The ranked pixel encoders, then the references apart (unranked), then which entries read another data set
    than `shared`, the board's (`selection.shared_dataset` of its runs)."""
    ranked = [e for e in board if e.reference is None]
    references = [e for e in board if e.reference is not None]
    headers = ["rank", "encoder", f"{rank.label} (mean ± std)", "IQM [95% CI]", "seeds", "reads", "data set",
               "encoder code", "date"]
    rows = [[str(i), e.encoder, rank.format(e.stats), rank.format_iqm(e.stats), str(e.stats.n), e.reads,
             dataset_label(e), e.version, e.date] for i, e in enumerate(ranked, 1)]
    text = tabulate(rows, headers=headers, tablefmt="github", disable_numparse=True) if rows else (
        "No pixel encoder has runs here.")
    if references:
        rows = [[e.encoder, e.reference, rank.format(e.stats), rank.format_iqm(e.stats), str(e.stats.n),
                 dataset_label(e), e.version, e.date] for e in references]
        text += "\n\nReferences (not ranked):\n\n" + tabulate(
            rows, headers=["encoder", "role", f"{rank.label} (mean ± std)", "IQM [95% CI]", "seeds", "data set",
                           "encoder code", "date"], tablefmt="github", disable_numparse=True)
    if any(e.other_dataset for e in board):
        text += f"\n\nNot one data set. {other_dataset_note('Entries')} Most of this board's runs read {shared}."
    return text


def by_task_and_preset(runs: Iterable[RunRecord]) -> dict[str, dict[str, list[RunRecord]]]:
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
            f"interval (rliable), given from {IQM_MIN_SEEDS} seeds on. Only runs of the current spec files count "
            f"(an overridden embedding size is its own entry), and of those only the runs of one encoder code, "
            f"one task code and one data set (the entry's latest); of repeated runs of one seed the latest "
            f"counts. Reads: the encoder's inputs (pixels, and `action` for one that also reads the recorded "
            f"actions). References (encoders that read the true state, the scorecard's floor and ceiling) are "
            f"listed apart, not ranked. Encoder code: the distribution and version that shipped the encoder (a "
            f"plugin's own). Data set: the fingerprint of the data set the entry's runs read (`-`: none), marked * "
            f"when it is not the one most of the board's runs read. Date: the latest of the entry's "
            f"runs.")


_INDEX_TITLE = "# Leaderboards"


def overall_cards(records: Sequence[RunRecord], accept: Accept = matches_current_specs) -> list[scorecard.Scorecard]:
    """The scorecards of the table presets (paper, then quick) that score at least one pixel encoder."""
    cards = [scorecard.build(records, preset, accept=accept) for preset in TABLE_PRESETS]
    return [card for card in cards if card.ranked]


def render_boards(records: Iterable[RunRecord], accept: Accept = matches_current_specs) -> dict[str, str]:
    """File name -> markdown text: `<task>.md` for each task with a ranking, and `README.md`."""
    records = list(records)
    files: dict[str, str] = {}
    index = [_INDEX_TITLE, "",
             "Generated by `mftcn-bench leaderboard` from the results store; do not edit by hand. Results "
             "travel between machines as JSON files (`mftcn-bench results export DIR` / `results import DIR`).",
             "", "## Overall", "",
             "The scorecard (`mftcn-bench report scorecard --preset <name>`): every task's result normalised "
             "between random state (0) and true state (1), aggregated over tasks with rliable.", ""]
    for card in overall_cards(records, accept):
        index += [scorecard.render(card), ""]
    index += ["## Per task", "", "| task | ranked by | preset | best pixel encoder | seeds |", "|---|---|---|---|---|"]
    unranked = []
    for task, presets in by_task_and_preset(counted_runs(records, accept)).items():
        rank = ranking(task)
        if rank is None:
            unranked.append(task)
            continue
        direction = "higher" if rank.higher_is_better else "lower"
        lines = [f"# {task}", "", _explain(rank)]
        for preset, runs in presets.items():
            board = entries(runs, rank)
            lines += ["", f"## preset `{preset}`", "", _board(rank, board, shared_dataset(runs))]
            best = next((e for e in board if e.reference is None), None)
            index.append(f"| [{task}]({task}.md) | {rank.label} ({direction} is better) | {preset} | "
                         + (f"{best.encoder}: {rank.format(best.stats)} | {best.stats.n} |" if best
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
