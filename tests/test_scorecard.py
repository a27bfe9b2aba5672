"""The scorecard against hand-computed scores, and rliable's estimates against brute force."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from scipy.stats import trim_mean

from mftcn_bench.cli import main
from mftcn_bench.results import scorecard
from mftcn_bench.results.intervals import aggregates, improvement_probability
from tests.records import make_record, probe_config

R2 = ("r2_x_cart", "r2_sin_theta", "r2_cos_theta", "r2_x_dot", "r2_theta_dot")


def probe_runs(encoder: str, r2s: list[float], preset: str = "quick") -> list:
    return [make_record(encoder, "cartpole-probe", seed, {"average": 1.0 - r2, **dict.fromkeys(R2, r2)},
                        preset=preset, config=probe_config(encoder, preset)) for seed, r2 in enumerate(r2s)]


def swingup_runs(encoder: str, returns: list[float]) -> list:
    return [make_record(encoder, "swingup", seed, {"return_mean": value},
                        config={"encoder": {"name": encoder}, "task": {"name": "swingup"}})
            for seed, value in enumerate(returns)]


def records() -> list:
    return [*probe_runs("random-state", [0.0, 0.0, 0.0]), *probe_runs("true-state", [1.0, 1.0, 1.0]),
            *probe_runs("mftcn5", [0.5, 0.6, 0.7]), *probe_runs("mftcn1", [0.2, 0.3, 0.4]),
            *probe_runs("pve", [0.4, 0.8, 0.9]),
            *swingup_runs("random-state", [100.0, 100.0, 100.0]), *swingup_runs("true-state", [900.0, 900.0, 900.0]),
            *swingup_runs("mftcn5", [500.0, 580.0, 660.0]), *swingup_runs("mftcn1", [300.0, 340.0, 420.0])]


@pytest.fixture(scope="module")
def built() -> scorecard.Scorecard:
    return scorecard.build(records(), "quick", accept=lambda r: True)


def test_scores_are_normalised_between_the_floor_and_the_ceiling_of_each_task(built):
    card = built
    rows = {r.encoder: r for r in card.rows}
    assert rows["mftcn5"].cells["cartpole-probe"].scores == pytest.approx((0.5, 0.6, 0.7))  # R^2 scale 0..1
    assert rows["mftcn5"].cells["swingup"].scores == pytest.approx((0.5, 0.6, 0.7))  # (x - 100) / 800
    assert rows["mftcn1"].cells["swingup"].scores == pytest.approx((0.25, 0.3, 0.4))
    assert {r.encoder for r in card.references} == {"random-state", "true-state"}  # apart, as references
    assert [r.encoder for r in card.ranked] == ["mftcn5", "mftcn1", "pve"]  # pve: one task, after two


def test_the_aggregate_is_the_iqm_and_mean_over_every_run_of_the_tasks(built):
    row = next(r for r in built.rows if r.encoder == "mftcn1")
    runs = [0.2, 0.3, 0.4, 0.25, 0.3, 0.4]
    assert row.aggregated == ("cartpole-probe", "swingup")
    assert row.aggregate.iqm.value == pytest.approx(trim_mean(runs, 0.25))
    assert row.aggregate.mean.value == pytest.approx(np.mean(runs))
    assert row.aggregate.iqm.low <= row.aggregate.iqm.value <= row.aggregate.iqm.high


def test_probability_of_improvement_is_the_mann_whitney_statistic_averaged_over_tasks(built):
    x = np.array([[0.5, 0.9], [0.6, 0.1], [0.7, 0.4]])
    y = np.array([[0.2, 0.4], [0.6, 0.3], [0.4, 0.8]])
    brute = np.mean([np.mean([1.0 if a > b else 0.5 if a == b else 0.0
                              for a, b in itertools.product(x[:, t], y[:, t])]) for t in range(2)])
    estimate = improvement_probability(x, y)
    assert estimate.value == pytest.approx(brute)
    assert 0.0 <= estimate.low <= estimate.value <= estimate.high <= 1.0
    row = next(r for r in built.rows if r.encoder == "mftcn1")
    assert row.improvement.value == 0.0 and row.improvement_tasks == ("cartpole-probe", "swingup")


def test_intervals_are_deterministic_and_stratified_by_task():
    scores = {"a": np.array([[0.1, 5.0], [0.2, 6.0], [0.3, 7.0]])}
    first, second = aggregates(scores)["a"], aggregates(scores)["a"]
    assert first == second
    # Runs are resampled within each task: every resample keeps one value per task and run, so the mean
    # stays between the task means' extremes.
    assert 0.1 + 5.0 <= 2 * first.mean.low and 2 * first.mean.high <= 0.3 + 7.0


def test_a_task_without_floor_or_ceiling_runs_is_named_not_scored():
    runs = [r for r in records() if not (r.task == "swingup" and r.encoder == "random-state")]
    result = scorecard.build(runs, "quick", accept=lambda r: True)
    assert result.unscored["swingup"] == "no random-state runs"
    assert "Not scored at this preset: swingup (no random-state runs)" in scorecard.render(result)


def test_the_render_says_how_many_runs_and_tasks_each_figure_rests_on(built, tmp_path):
    text = scorecard.render(built)
    rows = {cells[1]: cells for line in text.splitlines() if line.startswith("| ")
            and len(cells := [c.strip() for c in line.split("|")[1:-1]]) > 3}
    assert rows["mftcn1"][:2] == ["2", "mftcn1"] and rows["mftcn1"][4] == "2: cartpole-probe, swingup"
    assert rows["mftcn1"][5].startswith("0.00 [") and rows["mftcn1"][5].endswith("on 2")
    assert rows["pve"][4] == "1: cartpole-probe"
    assert "| cartpole-probe | R^2 (mean of 5 state variables) | 0 " in text  # the scale and its runs
    assert scorecard.plot_profiles(built, tmp_path / "p.png").stat().st_size > 1000


def test_a_cell_on_another_recording_than_its_tasks_latest_run_is_marked(built):
    assert not any(c.other_dataset for r in built.rows for c in r.cells.values())
    assert "another recording" not in scorecard.render(built)
    older = [dataclasses.replace(r, dataset_id="older0recording0", created_at="2025-12-01T00:00:00+00:00")
             if r.encoder == "mftcn1" and r.task == "swingup" else r for r in records()]
    card = scorecard.build(older, "quick", accept=lambda r: True)
    marked = {(r.encoder, t) for r in card.rows for t, c in r.cells.items() if c.other_dataset}
    assert marked == {("mftcn1", "swingup")}  # the others read the data set most runs read
    text = scorecard.render(card)
    assert "| 0.32 (3) *" in text and "Cells marked * rest on another recording" in text


def test_asked_for_encoders_are_scored_with_the_floor_ceiling_and_baseline():
    only = scorecard.build(records(), "quick", ["mftcn1"], accept=lambda r: True)
    assert {r.encoder for r in only.rows} == {"mftcn1", "mftcn5", "random-state", "true-state"}


def test_report_scorecard_refuses_an_unknown_encoder_in_one_line(capsys):
    assert main(["report", "scorecard", "--encoders", "mftcn5,nosuch"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nosuch" in err[0]
    assert main(["report", "probe", "--encoders", "mftcn5"]) == 2
