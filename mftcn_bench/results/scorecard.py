"""The scorecard: one normalised score per encoder and task, aggregated over tasks (rliable).

On each task of `reports/scorecard.toml` and one preset, a run's score is (x - floor) / (ceiling - floor),
where x is the task's scored metric and floor and ceiling are the means of the floor's and the ceiling's
counted runs there (random state scores 0, true state 1; an error metric works the same way, its ceiling
below its floor). A cell is an encoder's runs on one task. An encoder's aggregate is over every run of the
tasks where it has the spec's `runs` runs: the interquartile mean and mean with stratified-bootstrap
intervals, and its probability of improvement over the baseline encoder on the tasks both have. Runs are
the ones a board counts (`results.selection`: today's specs, one code and one data set per row); a cell on
another recording of its task's data than most of the task's runs read is marked, as on the boards.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tabulate import tabulate

from mftcn_bench.core.errors import SpecError
from mftcn_bench.results.intervals import (
    Aggregates,
    Estimate,
    aggregates,
    improvement_probability,
    scorecard_spec,
    settings,
)
from mftcn_bench.results.ranking import ranking
from mftcn_bench.results.references import anchors, privileged_of, reference_role
from mftcn_bench.results.selection import (
    Accept,
    counted_runs,
    left_out_line,
    matches_current_specs,
    other_dataset_note,
    overridden,
    shared_dataset,
)
from mftcn_bench.results.stats import format_number
from mftcn_bench.results.store import RunRecord


@dataclass(frozen=True)
class TaskScoring:
    """What is scored on one task: a metric (or the mean of several) and its direction."""

    task: str
    metrics: tuple[str, ...]
    higher_is_better: bool
    label: str

    def value(self, record: RunRecord) -> float | None:
        values = [record.metrics.get(m) for m in self.metrics]
        if any(not isinstance(v, int | float) or not np.isfinite(v) for v in values):
            return None
        return float(np.mean(values))


def task_scorings() -> list[TaskScoring]:
    """The scorecard's tasks in spec order: each its `[tasks.<name>]` table over the task's `[leaderboard]`."""
    out = []
    for task, table in scorecard_spec().get("tasks", {}).items():
        rank = ranking(task)
        metric = table.get("metric", rank.metric if rank else None)
        if metric is None:
            raise SpecError(f"scorecard spec: task {task!r} names no metric and has no [leaderboard] table")
        metrics = (metric,) if isinstance(metric, str) else tuple(metric)
        higher = table.get("higher_is_better", rank.higher_is_better if rank else None)
        if not isinstance(higher, bool):
            raise SpecError(f"scorecard spec: task {task!r} needs higher_is_better = true/false")
        out.append(TaskScoring(task, metrics, higher, str(table.get("label", rank.label if rank else metric))))
    return out


@dataclass(frozen=True)
class Cell:
    """One encoder's runs on one task: normalised scores and raw values, by seed."""

    task: str
    seeds: tuple[int, ...]
    scores: tuple[float, ...]
    values: tuple[float, ...]
    run_ids: tuple[str, ...]
    other_dataset: bool = False   # its runs read another data set than most of the task's runs (`shared_dataset`)

    @property
    def mean(self) -> float:
        return float(np.mean(self.scores))


@dataclass(frozen=True)
class Anchor:
    """A task's scale: the floor's and ceiling's mean values and how many runs each rests on."""

    floor: float
    ceiling: float
    floor_runs: int
    ceiling_runs: int


@dataclass(frozen=True)
class Row:
    """One encoder on the scorecard."""

    encoder: str
    reference: str | None
    privileged: tuple[str, ...]
    cells: dict[str, Cell]
    aggregated: tuple[str, ...] = ()   # the tasks its aggregate counts (those with `runs` runs)
    aggregate: Aggregates | None = None
    improvement: Estimate | None = None  # over the baseline, on `improvement_tasks`
    improvement_tasks: tuple[str, ...] = ()


@dataclass(frozen=True)
class Scorecard:
    preset: str
    runs: int
    baseline: str
    tasks: list[TaskScoring]
    anchors: dict[str, Anchor]
    unscored: dict[str, str]   # task -> why it has no scale
    rows: list[Row]
    left_out: str | None = None
    profiles: dict[str, Any] = field(default_factory=dict)

    @property
    def ranked(self) -> list[Row]:
        """Pixel encoders with an aggregate, those over more tasks first (aggregates over other tasks do not
        compare), then by IQM; then those without one, by name."""
        rows = [r for r in self.rows if r.reference is None]
        return sorted(rows, key=lambda r: (r.aggregate is None, -len(r.aggregated), r.aggregated,
                                           -(r.aggregate.iqm.value if r.aggregate else 0), r.encoder))

    @property
    def references(self) -> list[Row]:
        return sorted((r for r in self.rows if r.reference is not None), key=lambda r: r.encoder)


def build(records: Iterable[RunRecord], preset: str = "paper", encoders: Sequence[str] | None = None,
          accept: Accept = matches_current_specs) -> Scorecard:
    """The scorecard of `preset` from `records` (every encoder with runs, or only `encoders`, with the
    floor, ceiling and baseline always)."""
    spec = scorecard_spec()
    floor, ceiling = anchors()
    baseline, runs_needed = str(spec["baseline"]), int(spec["runs"])
    records = list(records)
    counted = [r for r in counted_runs(records, accept) if r.preset == preset and not overridden(r)]
    scorings = task_scorings()
    by_task: dict[str, list[RunRecord]] = {}
    for record in counted:
        by_task.setdefault(record.task, []).append(record)

    scales: dict[str, Anchor] = {}
    unscored: dict[str, str] = {}
    for scoring in scorings:
        runs = by_task.get(scoring.task, [])
        low = [v for r in runs if r.encoder == floor and (v := scoring.value(r)) is not None]
        high = [v for r in runs if r.encoder == ceiling and (v := scoring.value(r)) is not None]
        missing = [name for name, values in ((floor, low), (ceiling, high)) if not values]
        if missing:
            unscored[scoring.task] = f"no {' or '.join(missing)} runs" if runs else "no runs"
        elif np.isclose(np.mean(low), np.mean(high)):
            unscored[scoring.task] = f"{floor} and {ceiling} score the same"
        else:
            scales[scoring.task] = Anchor(float(np.mean(low)), float(np.mean(high)), len(low), len(high))

    wanted = None if encoders is None else {*encoders, floor, ceiling, baseline}
    cells: dict[str, dict[str, Cell]] = {}
    example: dict[str, RunRecord] = {}
    for scoring in scorings:
        scale = scales.get(scoring.task)
        if scale is None:
            continue
        shared = shared_dataset(by_task.get(scoring.task, []))
        for record in sorted(by_task.get(scoring.task, []), key=lambda r: (r.encoder, r.seed)):
            value = scoring.value(record)
            if value is None or (wanted is not None and record.encoder not in wanted):
                continue
            score = (value - scale.floor) / (scale.ceiling - scale.floor)
            cell = cells.setdefault(record.encoder, {}).get(scoring.task)
            cells[record.encoder][scoring.task] = Cell(
                scoring.task, (*(cell.seeds if cell else ()), record.seed), (*(cell.scores if cell else ()), score),
                (*(cell.values if cell else ()), value), (*(cell.run_ids if cell else ()), record.run_id),
                bool(record.dataset_id) and record.dataset_id != shared)
            example.setdefault(record.encoder, record)

    def matrix(encoder: str, tasks: Sequence[str]) -> np.ndarray:
        return np.array([cells[encoder][t].scores[:runs_needed] for t in tasks]).T  # [runs, tasks]

    full = {e: tuple(t for t in cells[e] if len(cells[e][t].scores) >= runs_needed) for e in cells}
    with_aggregate = {e: tasks for e, tasks in full.items() if tasks}
    estimates = aggregates({e: matrix(e, tasks) for e, tasks in with_aggregate.items()}) if with_aggregate else {}
    rows = []
    for encoder in sorted(cells):
        improvement, common = None, ()
        if encoder != baseline and baseline in full:
            common = tuple(t for t in full[encoder] if t in full[baseline])
            if common:
                improvement = improvement_probability(matrix(encoder, common), matrix(baseline, common))
        rows.append(Row(encoder, reference_role(example[encoder]), privileged_of(example[encoder]), cells[encoder],
                        full[encoder], estimates.get(encoder), improvement, common))
    return Scorecard(preset, runs_needed, baseline, scorings, scales, unscored, rows,
                     left_out_line(records, accept))


def _score(value: float) -> str:
    return f"{value:.2f}"


def _interval(estimate: Estimate | None) -> str:
    if estimate is None:
        return "-"
    return f"{_score(estimate.value)} [{_score(estimate.low)}, {_score(estimate.high)}]"


def _cell(cell: Cell | None) -> str:
    return "-" if cell is None else f"{_score(cell.mean)} ({len(cell.scores)})" + (" *" if cell.other_dataset else "")


def render(card: Scorecard) -> str:
    """The scorecard as markdown: the overall board (pixel encoders ranked by aggregate IQM), the references,
    the cells, and how every figure was made."""
    scored = [t for t in card.tasks if t.task in card.anchors]
    level = int(round(settings().confidence * 100))
    lines = [f"### Scorecard, preset `{card.preset}`", ""]
    headers = ["rank", "encoder", f"IQM [{level}% CI]", f"mean [{level}% CI]", f"tasks ({card.runs} runs each)",
               f"P(better than {card.baseline}) [{level}% CI]", "reads"]

    def aggregate_row(row: Row) -> list[str]:
        tasks = f"{len(row.aggregated)}: {', '.join(row.aggregated)}" if row.aggregated else "none"
        versus = "-" if row.improvement is None else f"{_interval(row.improvement)} on {len(row.improvement_tasks)}"
        return [row.encoder, _interval(row.aggregate.iqm if row.aggregate else None),
                _interval(row.aggregate.mean if row.aggregate else None), tasks, versus,
                ", ".join(("pixels", *row.privileged))]

    ranked = [[str(i) if r.aggregate else "-", *aggregate_row(r)] for i, r in enumerate(card.ranked, 1)]
    lines += [tabulate(ranked, headers=headers, tablefmt="github", disable_numparse=True) if ranked
              else "No pixel encoder has runs on a scored task.", ""]
    if card.references:
        refs = [[r.encoder, r.reference or "", *aggregate_row(r)[1:4]] for r in card.references]
        lines += ["References (not ranked):", "",
                  tabulate(refs, headers=["encoder", "role", *headers[2:5]], tablefmt="github",
                           disable_numparse=True), ""]
    if scored:
        cell_rows = [[r.encoder, *(_cell(r.cells.get(t.task)) for t in scored)]
                     for r in [*card.ranked, *card.references]]
        lines += [f"Normalised score per task (mean over runs, runs in brackets; 0 = {anchors()[0]}, "
                  f"1 = {anchors()[1]}):", "",
                  tabulate(cell_rows, headers=["encoder", *(t.task for t in scored)], tablefmt="github",
                           disable_numparse=True), ""]
        if any(c.other_dataset for r in card.rows for c in r.cells.values()):
            lines += [other_dataset_note("Cells"), ""]
        scale = [[t.task, t.label, _raw(card.anchors[t.task].floor), str(card.anchors[t.task].floor_runs),
                  _raw(card.anchors[t.task].ceiling), str(card.anchors[t.task].ceiling_runs)] for t in scored]
        lines += ["Scales:", "", tabulate(scale, headers=["task", "scored by", "floor", "runs", "ceiling", "runs"],
                                          tablefmt="github", disable_numparse=True), ""]
    if card.unscored:
        lines += ["Not scored at this preset: " + "; ".join(f"{t} ({why})" for t, why in card.unscored.items())
                  + ".", ""]
    lines.append(
        f"A run's score is (x - floor) / (ceiling - floor) on its task, floor and ceiling the means of "
        f"{anchors()[0]}'s and {anchors()[1]}'s runs there. An aggregate counts every run of the tasks where the "
        f"encoder has {card.runs} runs (its first {card.runs} seeds); aggregates over other tasks do not compare, "
        f"so the ranking puts those over more tasks first, then orders by IQM; IQM: the mean of the middle half "
        f"of those runs. "
        f"P(better than {card.baseline}): the probability that a run of the encoder scores above a run of "
        f"{card.baseline} on the same task, averaged over the tasks both have {card.runs} runs on (their number "
        f"follows 'on'). Intervals: rliable's stratified bootstrap ({settings().bootstrap_reps} resamples, runs "
        f"resampled within each task). Runs counted as on the boards: today's spec files, one encoder code, one "
        f"task code and one data set per row.")
    if card.left_out:
        lines += ["", card.left_out]
    return "\n".join(lines)


def _raw(value: float) -> str:
    return format_number(value)


def plot_profiles(card: Scorecard, path: Path) -> Path | None:
    """The performance profiles (the fraction of an encoder's aggregated runs scoring above tau) of the
    ranked encoders and references as a PNG; None when no encoder has an aggregate."""
    from mftcn_bench.results.intervals import performance_profiles

    rows = [r for r in [*card.ranked, *card.references] if r.aggregated]
    if not rows:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    low, high, count = scorecard_spec()["profile_taus"]
    taus = np.linspace(float(low), float(high), int(count))
    scores = {r.encoder: np.array([r.cells[t].scores[:card.runs] for t in r.aggregated]).T for r in rows}
    profiles, intervals = performance_profiles(scores, taus)
    figure, axis = plt.subplots(figsize=(7, 4.2))
    for row in rows:
        style = "--" if row.reference else "-"
        axis.plot(taus, profiles[row.encoder], style, label=f"{row.encoder} ({len(row.aggregated)} tasks)")
        axis.fill_between(taus, intervals[row.encoder][0], intervals[row.encoder][1], alpha=0.15)
    axis.set_xlabel("normalised score τ")
    axis.set_ylabel("fraction of runs with score > τ")
    axis.set_title(f"Performance profiles, preset {card.preset}")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.tight_layout()
    figure.savefig(path, dpi=110, metadata={"Software": None})
    plt.close(figure)
    return path


def as_dict(card: Scorecard) -> Mapping[str, Any]:
    """The scorecard as plain data (the web leaderboard's)."""
    def estimate(e: Estimate | None) -> dict | None:
        return None if e is None else {"value": e.value, "low": e.low, "high": e.high}

    return {"preset": card.preset, "runs": card.runs, "baseline": card.baseline,
            "tasks": [t.task for t in card.tasks if t.task in card.anchors], "unscored": card.unscored,
            "rows": [{"encoder": r.encoder, "reference": r.reference, "privileged": list(r.privileged),
                      "aggregated": list(r.aggregated),
                      "iqm": estimate(r.aggregate.iqm if r.aggregate else None),
                      "mean": estimate(r.aggregate.mean if r.aggregate else None),
                      "improvement": estimate(r.improvement), "improvement_tasks": list(r.improvement_tasks),
                      "cells": {t: {"mean": c.mean, "runs": len(c.scores), "run_ids": list(c.run_ids)}
                                for t, c in r.cells.items()}}
                     for r in [*card.ranked, *card.references]]}
