"""The paper's tables from stored results: our figures (mean ± sample std over seeds, number of seeds)
beside the paper's, as markdown or LaTeX.

What each table holds is data in `paper_tables`; this module fills its rows from the store. A paper row
with no stored run shows "-" for ours. Unless a preset is named, a table shows the runs of the paper preset
and then of the quick one (`selection.TABLE_PRESETS`), each paper row once per preset that has runs, the
preset in its own column; a line names the stored runs of other presets it leaves aside. Stored runs of a
table's tasks that no paper row covers (another encoder, another embedding size) follow as extra rows marked
"(not in paper)", except in a table of chosen analyses (`PaperTable.other_runs` False), which names them in
a line instead.
"""

from __future__ import annotations

import re
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Literal

from tabulate import tabulate

from mftcn_bench.results.paper_tables import TABLES, PaperRow, PaperTable
from mftcn_bench.results.selection import (
    TABLE_PRESETS,
    VARIED,
    Accept,
    SpecDefaults,
    code_label,
    config_value,
    counted_runs,
    current_specs_varying,
    left_out_line,
    lookup,
    matches_current_specs,
    other_dataset_note,
    preset_order,
    shared_dataset,
    variant_key,
    variant_label,
)
from mftcn_bench.results.stats import STD_KIND, SeedStats, format_mean_std, seed_stats
from mftcn_bench.results.store import ResultStore, RunRecord

__all__ = ["TABLES", "ReportRow", "matches_current_specs", "render", "report", "table_rows"]

Format = Literal["markdown", "latex"]
NOT_IN_PAPER = "(not in paper)"
OTHER_DATASET = other_dataset_note("Seeds")


@dataclass(frozen=True)
class ReportRow:
    """One printed row: label cells, our encoder/task/preset, the seed statistics of each metric column,
    and the paper's figures (None: a row the paper does not have)."""

    labels: tuple[str, ...]
    encoder: str
    task: str
    preset: str | None
    seeds: int
    stats: tuple[SeedStats | None, ...]
    paper: tuple[float | None, ...] | None
    code: str = "-"   # the encoder's distribution and version (`selection.code_label`) of the rows' runs
    other_dataset: bool = False  # its runs read another data set than most runs of its (task, preset)


def _row_matches(table: PaperTable, row: PaperRow, record: RunRecord, defaults: SpecDefaults) -> bool:
    if record.encoder != row.encoder or record.task != row.task:
        return False
    default = defaults(record)
    if default is None:
        return False
    # A varied key the row does not name must have its default: an overridden value is another row.
    where = {key: lookup(default, key) for key in table.varied} | dict(row.where)
    return all(config_value(record, key) == value for key, value in where.items())


def _stats(table: PaperTable, runs: Sequence[RunRecord]) -> tuple[SeedStats | None, ...]:
    return tuple(seed_stats(r.metrics.get(c.metric) for r in runs) for c in table.columns)


def _code(runs: Sequence[RunRecord]) -> str:
    return ", ".join(sorted({code_label(r) for r in runs})) or "-"


def _by_preset(runs: Iterable[RunRecord]) -> dict[str, list[RunRecord]]:
    groups: dict[str, list[RunRecord]] = defaultdict(list)
    for record in runs:
        groups[record.preset].append(record)
    return dict(sorted(groups.items(), key=lambda item: preset_order(item[0])))


def _in_view(table: PaperTable, record: RunRecord, preset: str | None) -> bool:
    """Whether `record` is of `table`'s tasks and of `preset` (None: of a table preset)."""
    return record.task in table.tasks and (record.preset in TABLE_PRESETS if preset is None
                                           else record.preset == preset)


def _counted(table: PaperTable, records: Iterable[RunRecord], preset: str | None,
             accept: Accept | None) -> list[RunRecord]:
    accept = accept or current_specs_varying(table.varied)
    return [r for r in counted_runs(records, accept, table.varied) if _in_view(table, r, preset)]


def _uncovered(table: PaperTable, runs: Sequence[RunRecord],
               defaults: SpecDefaults) -> dict[tuple, list[RunRecord]]:
    """The counted runs that no row of `table` covers, by variant."""
    groups: dict[tuple, list[RunRecord]] = defaultdict(list)
    for record in runs:
        if not any(_row_matches(table, row, record, defaults) for row in table.rows):
            groups[variant_key(record, table.varied)].append(record)
    return groups


def table_rows(table: PaperTable, records: Iterable[RunRecord], preset: str | None = None,
               accept: Accept | None = None) -> list[ReportRow]:
    """The table's rows from `records`: each paper row once per preset that has runs for it, paper before
    quick (or once with "-" when none has), then (if the table shows them) the runs no paper row covers.
    `preset` None: the table presets (`TABLE_PRESETS`). By default the runs of today's specs count, with at
    most the table's `varied` keys overridden."""
    runs = _counted(table, records, preset, accept)
    defaults = SpecDefaults()
    by_board: dict[tuple[str, str], list[RunRecord]] = defaultdict(list)
    for record in runs:
        by_board[record.task, record.preset].append(record)
    shared = {key: shared_dataset(group) for key, group in by_board.items()}

    def other(group: Sequence[RunRecord]) -> bool:
        first = group[0]
        return bool(first.dataset_id) and first.dataset_id != shared[first.task, first.preset]

    rows: list[ReportRow] = []
    for paper_row in table.rows:
        groups = _by_preset(r for r in runs if _row_matches(table, paper_row, r, defaults))
        if not groups:
            rows.append(ReportRow(paper_row.labels, paper_row.encoder, paper_row.task, preset, 0,
                                  (None,) * len(table.columns), paper_row.paper))
        for preset_name, group in groups.items():
            rows.append(ReportRow(paper_row.labels, paper_row.encoder, paper_row.task, preset_name, len(group),
                                  _stats(table, group), paper_row.paper, _code(group), other(group)))
    if not table.other_runs:
        return rows
    blank = ("",) * (len(table.label_headers) - 1)
    for group in _uncovered(table, runs, defaults).values():
        first = group[0]
        rows.append(ReportRow((NOT_IN_PAPER, *blank), variant_label(first, table.varied), first.task, first.preset,
                              len(group), _stats(table, group), None, _code(group), other(group)))
    return rows


def not_shown_line(table: PaperTable, records: Iterable[RunRecord], preset: str | None = None,
                   accept: Accept | None = None) -> str | None:
    """For a table that shows no "(not in paper)" rows: `Not shown: 2 counted runs that no row covers
    (pve on swingup, ...).`, so that nothing a table leaves aside goes unsaid; None when there are none."""
    if table.other_runs:
        return None
    groups = _uncovered(table, _counted(table, records, preset, accept), SpecDefaults())
    if not groups:
        return None
    total = sum(len(g) for g in groups.values())
    names = ", ".join(f"{variant_label(g[0], table.varied)} on {g[0].task}" for g in groups.values())
    return f"Not shown: {total} counted run{'s' if total > 1 else ''} that no row covers ({names})."


def other_presets_line(table: PaperTable, records: Iterable[RunRecord]) -> str | None:
    """For a table of the default presets: `Not shown: 3 stored runs of preset demo (`report probe --preset
    demo` shows them).`; None when every stored run of its tasks is of a table preset."""
    counts = Counter(r.preset for r in records if r.task in table.tasks and r.preset not in TABLE_PRESETS)
    if not counts:
        return None
    total = sum(counts.values())
    names = ", ".join(f"{name} ({n})" if len(counts) > 1 else name
                      for name, n in sorted(counts.items(), key=lambda item: preset_order(item[0])))
    first = min(counts, key=preset_order)
    return (f"Not shown: {total} stored run{'s' if total > 1 else ''} of preset{'s' if len(counts) > 1 else ''} "
            f"{names} (`report {table.name} --preset {first}` shows them).")


_LATEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#", "$": r"\$",
                  "^": r"\^{}", "~": r"\~{}", "{": r"\{", "}": r"\}"}


def _latex_escape(text: str) -> str:
    return re.sub("[" + re.escape("".join(_LATEX_SPECIAL)) + "]", lambda m: _LATEX_SPECIAL[m.group()], text)


def _cell(stats: SeedStats | None, paper: float | None, has_paper: bool, decimals: int, fmt: Format) -> str:
    ours = format_mean_std(stats, decimals, pm="$\\pm$" if fmt == "latex" else "±")
    if not has_paper:
        return ours
    return f"{ours} ({'-' if paper is None else f'{paper:.{decimals}f}'})"


def render(table: PaperTable, rows: Sequence[ReportRow], fmt: Format = "markdown") -> str:
    """The table as text: a title, what the figures are, and the rows."""
    multi_task = len(table.tasks) > 1
    headers = [*table.label_headers, "encoder", *(["task"] if multi_task else []), "preset", "seeds",
               *(c.label for c in table.columns), "encoder code"]
    body = []
    for row in rows:
        cells = [_cell(s, row.paper[i] if row.paper else None, row.paper is not None, table.decimals, fmt)
                 for i, s in enumerate(row.stats)]
        labels = [*row.labels, row.encoder, *([row.task] if multi_task else []), row.preset or "-",
                  f"{row.seeds} *" if row.other_dataset else str(row.seeds)]
        if fmt == "latex":
            labels = [_latex_escape(text) for text in labels]
        body.append([*labels, *cells, _latex_escape(row.code) if fmt == "latex" else row.code])
    overridable = ("embedding size" if table.varied == VARIED else
                   ", ".join(key.replace("encoder.embedding_dim", "embedding size") for key in table.varied))
    explain = (f"Ours: mean ± {STD_KIND} (seeds = n); the paper's figure in brackets, \"-\" where it has "
               f"none. Only runs of the current spec files count ({overridable} may be overridden). "
               f"{table.note}").strip()
    if fmt == "latex":
        headers = [_latex_escape(h) for h in headers]
        text = tabulate(body, headers=headers, tablefmt="latex_raw", disable_numparse=True)
        marked = f" {OTHER_DATASET}" if any(row.other_dataset for row in rows) else ""
        caption = _latex_escape(f"{table.title}. {explain}{marked}").replace("±", "$\\pm$")
        return f"\\begin{{table}}[h]\n\\caption{{{caption}}}\n\\centering\n{text}\n\\end{{table}}"
    text = tabulate(body, headers=headers, tablefmt="github", disable_numparse=True)
    if any(row.other_dataset for row in rows):
        text += f"\n\n{OTHER_DATASET}"
    return f"### {table.title}\n\n{explain}\n\n{text}"


def report(store: ResultStore, names: Sequence[str], preset: str | None = None, fmt: Format = "markdown",
           accept: Accept | None = None) -> str:
    """The named tables (see TABLES) rendered from `store` (`preset` None: the table presets), each followed
    by the lines saying which of its tasks' stored runs it left out, separated by blank lines."""
    records = store.query(preset=preset)
    parts = []
    for name in names:
        table = TABLES[name]
        parts.append(render(table, table_rows(table, records, preset, accept), fmt))
        skipped = left_out_line([r for r in records if _in_view(table, r, preset)],
                                accept or current_specs_varying(table.varied), table.varied)
        other_presets = None if preset is not None else other_presets_line(table, records)
        for line in (skipped, not_shown_line(table, records, preset, accept), other_presets):
            if line:
                parts.append(f"% {line}" if fmt == "latex" else line)
    return "\n\n".join(parts)
