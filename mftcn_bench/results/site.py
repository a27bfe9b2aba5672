"""The web leaderboard: one self-contained static `index.html` (`mftcn-bench leaderboard --html DIR`).

The page holds the overall boards (the scorecards of the table presets, their performance profiles inline as
PNG data) and every per-task board, with the paper's figure beside each row where the paper has one. Columns
sort on a click, and a filter shows one task family (a task name's first word: cartpole, swingup, cheetah,
pouring, imitate) or one preset. Each entry links to the run records behind it, copied beside the page under
`records/`. Nothing is fetched at view time: the script and styles are inline and written here (a page this
small needs no framework), so the folder opens from disk or from any static host.
"""

from __future__ import annotations

import base64
import html
import json
import shutil
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import asdict
from pathlib import Path

from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.results import scorecard
from mftcn_bench.results.leaderboard import Entry, by_task_and_preset, dataset_label, entries, overall_cards
from mftcn_bench.results.paper_tables import TABLES
from mftcn_bench.results.ranking import Ranking, ranking
from mftcn_bench.results.selection import (
    Accept,
    counted_runs,
    left_out_line,
    matches_current_specs,
    other_dataset_note,
)
from mftcn_bench.results.store import RunRecord


def paper_figure(encoder: str, task: str, metric: str) -> float | None:
    """The paper's figure for an encoder's default configuration on a task's metric, if the paper has one."""
    for table in TABLES.values():
        for row in table.rows:
            if row.encoder != encoder or row.task != task or row.where or row.paper is None:
                continue
            for column, value in zip(table.columns, row.paper, strict=True):
                if column.metric == metric and value is not None:
                    return value
    return None


def family(task: str) -> str:
    return task.split("-")[0]


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


def _links(run_ids: Sequence[str]) -> str:
    return " ".join(f'<a href="records/{_e(r)}.json">{i}</a>' for i, r in enumerate(run_ids))


def _value_cell(text: str, value: float | None) -> str:
    sort = "" if value is None else f' data-sort="{value!r}"'
    return f"<td{sort}>{_e(text)}</td>"


def _entry_row(rank: Ranking, entry: Entry, place: str, task: str) -> str:
    paper = paper_figure(entry.encoder, task, rank.metric)
    paper_text = "-" if paper is None else (f"{paper:.{rank.decimals}f}" if rank.decimals is not None
                                            else f"{paper:g}")
    role = entry.reference or ""
    return ("<tr>" + f'<td data-sort="{place or 1e9}">{_e(place or "ref")}</td>'
            + f'<td class="encoder">{_e(entry.encoder)}</td>'
            + _value_cell(rank.format(entry.stats), entry.stats.mean)
            + _value_cell(rank.format_iqm(entry.stats), entry.stats.iqm)
            + f'<td data-sort="{entry.stats.n}">{entry.stats.n}</td>'
            + _value_cell(paper_text, paper)
            + f"<td>{_e(role or entry.reads)}</td><td>{_e(dataset_label(entry))}</td><td>{_e(entry.version)}</td>"
            + f"<td>{_e(entry.date)}</td>"
            + f'<td class="records">{_links(entry.run_ids)}</td></tr>')


def _task_board(task: str, preset: str, rank: Ranking, board: Sequence[Entry]) -> str:
    ranked = [e for e in board if e.reference is None]
    references = [e for e in board if e.reference is not None]
    better = "higher" if rank.higher_is_better else "lower"
    other = "; " + _e(other_dataset_note("Entries")) if any(e.other_dataset for e in board) else ""
    rows = [_entry_row(rank, e, str(i), task) for i, e in enumerate(ranked, 1)]
    rows += [_entry_row(rank, e, "", task) for e in references]
    headers = ["rank", "encoder", f"{rank.label} (mean ± std)", "IQM [95% CI]", "seeds", "paper", "reads / role",
               "data set", "encoder code", "date", "records (by seed)"]
    return (f'<section class="board" data-family="{_e(family(task))}" data-preset="{_e(preset)}" '
            f'data-task="{_e(task)}"><h3>{_e(task)} <small>preset {_e(preset)}; {_e(rank.label)}, {better} is '
            f"better; references (ref) are listed, not ranked{other}"
            f"</small></h3>{_table(headers, rows)}</section>")


def _table(headers: Sequence[str], rows: Sequence[str]) -> str:
    head = "".join(f'<th data-column="{i}" title="sort">{_e(h)}</th>' for i, h in enumerate(headers))
    return f'<table class="sortable"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'


def _interval_cell(estimate: scorecard.Estimate | None) -> str:
    if estimate is None:
        return "<td>-</td>"
    return _value_cell(f"{estimate.value:.2f} [{estimate.low:.2f}, {estimate.high:.2f}]", estimate.value)


def _score_cell(cell: scorecard.Cell | None) -> str:
    if cell is None:
        return "<td>-</td>"
    return _value_cell(f"{cell.mean:.2f} ({len(cell.scores)})" + (" *" if cell.other_dataset else ""), cell.mean)


def _overall(card: scorecard.Scorecard, profile: Path | None) -> str:
    rows = []
    for i, row in enumerate([*card.ranked, *card.references], 1):
        place = "ref" if row.reference else (str(i) if row.aggregate else "-")
        links = " ".join(f'<a href="records/{_e(r)}.json">{_e(t)} {s}</a>' for t, cell in row.cells.items()
                         for s, r in zip(cell.seeds, cell.run_ids, strict=True))
        count = sum(len(cell.run_ids) for cell in row.cells.values())
        versus = "<td>-</td>" if row.improvement is None else _interval_cell(row.improvement)
        rows.append("<tr>" + f'<td data-sort="{i if not row.reference else 1e9}">{place}</td>'
                    + f'<td class="encoder">{_e(row.encoder)}</td>'
                    + _interval_cell(row.aggregate.iqm if row.aggregate else None)
                    + _interval_cell(row.aggregate.mean if row.aggregate else None)
                    + f'<td data-sort="{len(row.aggregated)}">{_e(", ".join(row.aggregated) or "none")}</td>'
                    + versus + f"<td>{_e(row.reference or ', '.join(('pixels', *row.privileged)))}</td>"
                    + "".join(_score_cell(row.cells.get(t)) for t in card.anchors)
                    + f'<td class="records"><details><summary>{count} runs</summary>{links}</details></td></tr>')
    headers = ["rank", "encoder", "IQM [95% CI]", "mean [95% CI]", f"tasks ({card.runs} runs each)",
               f"P(better than {card.baseline})", "reads / role", *card.anchors, "runs"]
    image = ""
    if profile is not None:
        data = base64.b64encode(profile.read_bytes()).decode()
        image = (f'<img class="profile" alt="performance profiles, preset {_e(card.preset)}" '
                 f'src="data:image/png;base64,{data}">')
    unscored = "; ".join(f"{t} ({why})" for t, why in card.unscored.items())
    marked = (" " + _e(other_dataset_note("Cells"))
              if any(c.other_dataset for r in card.rows for c in r.cells.values()) else "")
    return (f'<section class="board overall" data-family="all" data-preset="{_e(card.preset)}">'
            f"<h3>Overall, preset {_e(card.preset)} <small>normalised scores, 0 = random state, 1 = true state; "
            f"ranked by aggregate IQM over the tasks with {card.runs} runs, those over more tasks "
            f"first</small></h3>"
            f"{_table(headers, rows)}<p class=\"note\">Not scored: {_e(unscored or 'none')}.{marked}</p>{image}"
            "</section>")


_STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}h1{margin-bottom:.2em}
table{border-collapse:collapse;margin:.5em 0 1em;font-size:14px}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:left}
th{background:#f0f0f0;cursor:pointer;user-select:none}
th.asc::after{content:" \\25B2"}th.desc::after{content:" \\25BC"}
td.encoder{font-weight:600}small{font-weight:normal;color:#666}.note{color:#555;font-size:13px}
img.profile{max-width:640px;display:block}
.controls{margin:1em 0;padding:.5em;background:#fafafa;border:1px solid #ddd}
section.hidden{display:none}
"""

# Sorting: by a cell's data-sort number when it has one, else its text; the header keeps the direction.
# Filtering: a board shows when its family and preset match the selects ("all" matches every one).
_SCRIPT = """
function cellKey(row, i) {
  const c = row.children[i]; if (!c) return '';
  const s = c.getAttribute('data-sort'); return s === null ? c.textContent.trim() : parseFloat(s);
}
function sortTable(th) {
  const table = th.closest('table'), i = +th.dataset.column, body = table.tBodies[0];
  const asc = !th.classList.contains('asc');
  table.querySelectorAll('th').forEach(h => h.classList.remove('asc', 'desc'));
  th.classList.add(asc ? 'asc' : 'desc');
  const rows = Array.from(body.rows);
  rows.sort((a, b) => {
    const x = cellKey(a, i), y = cellKey(b, i);
    if (typeof x === 'number' && typeof y === 'number') return asc ? x - y : y - x;
    if (typeof x === 'number') return -1;
    if (typeof y === 'number') return 1;
    return asc ? String(x).localeCompare(y) : String(y).localeCompare(x);
  });
  rows.forEach(r => body.appendChild(r));
}
function applyFilter() {
  const f = document.getElementById('family').value, p = document.getElementById('preset').value;
  document.querySelectorAll('section.board').forEach(s => {
    const okF = f === 'all' || s.dataset.family === f || s.dataset.family === 'all';
    const okP = p === 'all' || s.dataset.preset === p;
    s.classList.toggle('hidden', !(okF && okP));
  });
}
document.querySelectorAll('th[data-column]').forEach(th=>th.addEventListener('click',()=>sortTable(th)));
document.getElementById('family').addEventListener('change',applyFilter);
document.getElementById('preset').addEventListener('change',applyFilter);
"""


def _select(name: str, label: str, values: Iterable[str]) -> str:
    options = "".join(f'<option value="{_e(v)}">{_e(v)}</option>' for v in ["all", *values])
    return f'<label>{_e(label)} <select id="{name}">{options}</select></label>'


def render_page(records: Iterable[RunRecord], cards: Sequence[scorecard.Scorecard],
                profiles: dict[str, Path | None], accept: Accept = matches_current_specs) -> str:
    """The page's HTML: the overall boards of `cards` (their performance-profile PNGs by preset in
    `profiles`), then every task's boards."""
    records = list(records)
    sections = [_overall(card, profiles.get(card.preset)) for card in cards]
    families, presets = set(), [card.preset for card in cards]
    for task, by_preset in by_task_and_preset(counted_runs(records, accept)).items():
        rank = ranking(task)
        if rank is None:
            continue
        families.add(family(task))
        for preset, runs in by_preset.items():
            presets.append(preset)
            sections.append(_task_board(task, preset, rank, entries(runs, rank)))
    presets = list(dict.fromkeys(presets))
    left_out = left_out_line(records, accept) or "Every stored run counts."
    return ("<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>mftcn-bench leaderboard</title>"
            f"<style>{_STYLE}</style></head><body><h1>mftcn-bench leaderboard</h1>"
            "<p class=\"note\">Generated by <code>mftcn-bench leaderboard --html</code> from the run records "
            "(linked under <code>records/</code>); do not edit by hand. Click a column to sort it.</p>"
            f'<div class="controls">{_select("family", "task family", sorted(families))} '
            f'{_select("preset", "preset", presets)}</div>' + "".join(sections)
            + f'<p class="note">{_e(left_out)}</p><script>{_SCRIPT}</script></body></html>')


def write_site(records: Iterable[RunRecord], out: Path, accept: Accept = matches_current_specs) -> Path:
    """Write `out/index.html` and `out/records/<run id>.json` for every run the page counts; returns the
    page's path."""
    records = list(records)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="mftcn-site-") as tmp:
        cards = overall_cards(records, accept)
        profiles = {card.preset: scorecard.plot_profiles(card, Path(tmp) / f"profile-{card.preset}.png")
                    for card in cards}
        page = render_page(records, cards, profiles, accept)
    folder = out / "records"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    for record in counted_runs(records, accept):
        (folder / f"{record.run_id}.json").write_text(json.dumps(asdict(record), indent=1, sort_keys=True))
    atomic_write_bytes(out / "index.html", page.encode())
    return out / "index.html"
