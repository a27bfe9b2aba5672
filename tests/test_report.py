"""The paper tables from stored runs: which runs count, rows, cells, formats."""

import copy
import dataclasses

import pytest

from mftcn_bench.core import registry
from mftcn_bench.core.specs import resolve_config
from mftcn_bench.results.paper_tables import TABLES
from mftcn_bench.results.report import NOT_IN_PAPER, matches_current_specs, render, report, table_rows
from mftcn_bench.results.store import ResultStore, RunRecord
from tests.records import make_record, probe_config


def record(config, encoder="mftcn4"):
    return RunRecord("id", encoder, "cartpole-probe", "smoke", 0, "d", config, {}, {}, {})


def test_only_runs_of_the_current_specs_are_tabled():
    _, config = resolve_config(registry.get("encoders", "mftcn4").spec,
                               registry.get("tasks", "cartpole-probe").spec, "smoke",
                               [("encoder.embedding_dim", 8)])
    assert matches_current_specs(record(config))
    stale = copy.deepcopy(config)
    stale["encoder"]["train"]["lr"] = 0.5
    assert not matches_current_specs(record(stale))
    other_task = copy.deepcopy(config)
    other_task["task"]["probe"]["epochs"] += 1
    assert not matches_current_specs(record(other_task))
    assert not matches_current_specs(record(config, encoder="uninstalled-plugin"))
    # keys that only add diagnostics (the held-out loss) do not retire the runs recorded before them
    older = copy.deepcopy(config)
    del older["encoder"]["train"]["heldout_every"], older["encoder"]["train"]["heldout_batches"]
    assert matches_current_specs(record(older))
    other_diagnostics = copy.deepcopy(config)
    other_diagnostics["encoder"]["train"]["heldout_batches"] += 1
    assert matches_current_specs(record(other_diagnostics))
    # keys added with the value that reproduces the earlier network: absent counts as that value
    added = copy.deepcopy(config)
    del added["encoder"]["model"]["temporal_kernel"], added["encoder"]["model"]["spatial_pool"]
    assert matches_current_specs(record(added))
    other_head = copy.deepcopy(config)
    other_head["encoder"]["model"]["spatial_pool"] = "mean+softargmax"
    assert not matches_current_specs(record(other_head))


# --- the paper tables, filled from synthetic stored runs -----------------------------------------------

def accept_all(record):
    return True


def line_of(text, *needles):
    lines = [line for line in text.splitlines() if all(n in line for n in needles)]
    assert len(lines) == 1, (needles, text)
    return lines[0]


def test_swingup_rows_mean_std_seeds_beside_the_paper():
    records = [make_record("mftcn5", "swingup", seed, {"return_mean": 700.0 + 10 * seed, "return_std": 50.0})
               for seed in range(3)]
    records.append(make_record("tcn", "swingup", 0, {"return_mean": 300.0, "return_std": 20.0}))
    records.append(make_record("mftcn5", "swingup-160", 0, {"return_mean": 790.0, "return_std": 60.0}))
    text = render(TABLES["swingup"], table_rows(TABLES["swingup"], records, accept=accept_all))
    row = line_of(text, "96x48", "mftcn5")
    assert "| 3 " in row and "710.00 ± 10.00 (701.30)" in row and "50.00 ± 0.00 (80.14)" in row
    assert "790.00 (787.47)" in line_of(text, "160x160", "mftcn5", "swingup-160 ")
    assert "- (861.41)" in line_of(text, "True State")  # a paper row with no stored run
    assert "300.00 " in line_of(text, NOT_IN_PAPER, "tcn")
    assert "ddof=1" in text


def test_a_row_on_another_recording_than_its_tasks_latest_run_is_marked():
    def run(encoder, task, seed, dataset, at):
        made = make_record(encoder, task, seed, {"return_mean": 500.0, "return_std": 50.0}, created_at=at)
        return dataclasses.replace(made, dataset_id=dataset)

    records = [*(run("mftcn5", "swingup", s, "new0recording000", "2026-03-05T10:00:00+00:00") for s in range(3)),
               run("mftcn1", "swingup", 0, "old0recording000", "2026-03-01T10:00:00+00:00"),
               run("pixels-cnn", "swingup", 0, None, "2026-03-09T10:00:00+00:00"),  # reads no data
               run("mftcn5", "swingup-160", 0, "other0task000000", "2026-03-01T10:00:00+00:00")]  # its own task
    text = render(TABLES["swingup"], table_rows(TABLES["swingup"], records, accept=accept_all))
    def seeds(line):
        cells = [c.strip() for c in line.split("|")[1:-1]]
        return cells[cells.index("quick") + 1]

    assert seeds(line_of(text, "96x48", "mftcn1")) == "1 *" and seeds(line_of(text, "96x48", "mftcn5")) == "3"
    assert seeds(line_of(text, "pixels-cnn")) == "1"
    assert seeds(line_of(text, "160x160", "mftcn5", "swingup-160 ")) == "1"
    assert "Seeds marked * rest on another recording" in text
    unmarked = render(TABLES["swingup"], table_rows(TABLES["swingup"], records[:3], accept=accept_all))
    assert "Seeds marked" not in unmarked


def test_probe_rows_are_matched_by_embedding_size_and_stale_runs_left_out():
    records = [make_record("mftcn4", "cartpole-probe", s, {"average": v}, config=probe_config("mftcn4", "quick", 8))
               for s, v in ((0, 0.02), (1, 0.04))]
    records.append(make_record("mftcn4", "cartpole-probe", 0, {"average": 9.0}, config=probe_config("mftcn4")))
    stale = probe_config("mftcn4", "quick", 8)
    stale["encoder"]["train"]["lr"] = 0.5
    records.append(make_record("mftcn4", "cartpole-probe", 2, {"average": 100.0}, config=stale))
    rows = {(r.labels, r.preset): r for r in table_rows(TABLES["probe"], records)}
    eight = rows[(("8", "4"), "quick")]
    assert eight.seeds == 2 and eight.stats[0].mean == pytest.approx(0.03) and eight.paper[0] == 0.0207
    assert rows[(("32", "4"), "quick")].stats[0].mean == 9.0
    assert rows[(("8", "1"), None)].seeds == 0


def test_latest_run_of_a_seed_counts():
    old = make_record("mftcn1", "pouring", 0, {"static_error": 40.0}, created_at="2026-01-01T00:00:00+00:00")
    new = make_record("mftcn1", "pouring", 0, {"static_error": 20.0}, created_at="2026-02-01T00:00:00+00:00")
    for order in ([old, new], [new, old]):  # the store returns oldest first; either way the latest counts
        (row,) = [r for r in table_rows(TABLES["pouring"], order, accept=accept_all) if r.encoder == "mftcn1"]
        assert row.seeds == 1 and row.stats[0].mean == 20.0


def test_pouring_attribute_columns_and_paper_dashes(tmp_path):
    metrics = {f"error_{a}": 10.0 for a in ("contact", "within_distance", "liquid_flowing", "has_liquid",
                                            "reaching", "receding", "going_up", "coming_down")}
    metrics["error_tilt_angle"] = 33.3
    store = ResultStore(tmp_path / "r.sqlite")
    store.put(make_record("tcn", "pouring", 0, metrics))
    text = report(store, ["pouring-attributes"], accept=accept_all)
    assert "33.3 (35.9)" in line_of(text, "| TCN")  # angle is the paper's second column
    assert "10.0 (-)" in line_of(text, "| TCN")  # the paper has no motion figures for TCN
    assert "- (37.5)" in line_of(text, "mfTCN^29")


def test_latex_format_escapes_and_uses_pm(tmp_path):
    store = ResultStore(tmp_path / "r.sqlite")
    for seed in (0, 1):
        store.put(make_record("mftcn13", "pouring", seed, {"static_error": 15.0 + seed, "motion_error": 20.0,
                                                           "alignment_error": 10.0}))
    text = report(store, ["pouring"], fmt="latex", accept=accept_all)
    assert text.startswith("\\begin{table}") and "\\begin{tabular}" in text
    assert "15.5 $\\pm$ 0.7 (16.8)" in text and "mfTCN\\^{}13" in text and "|" not in text


def test_every_table_renders_from_an_empty_store(tmp_path):
    text = report(ResultStore(tmp_path / "r.sqlite"), list(TABLES))
    assert text.count("### ") == len(TABLES) == 11
    assert "- (0.0198)" in text and "- (811.10)" in text and "- (8.9)" in text


def test_report_offers_every_table():
    from mftcn_bench.cli.results_commands import REPORT_CHOICES

    assert REPORT_CHOICES == [*TABLES, "scorecard", "all"]


def test_a_task_encoder_default_embedding_size_is_the_paper_row_not_an_override():
    # cheetah's spec gives true-state its 17-value state ([encoder_defaults.true-state])
    _, config = resolve_config(registry.get("encoders", "true-state").spec, registry.get("tasks", "cheetah").spec,
                               "quick")
    assert config["encoder"]["embedding_dim"] == 17
    run = make_record("true-state", "cheetah", 0, {"return_mean": 324.0, "return_std": 16.0}, config=config)
    text = render(TABLES["cheetah"], table_rows(TABLES["cheetah"], [run], accept=accept_all))
    assert "324.00 (390.16)" in line_of(text, "True State") and NOT_IN_PAPER not in text


def resolved(encoder, task, overrides=()):
    _, config = resolve_config(registry.get("encoders", encoder).spec, registry.get("tasks", task).spec, "quick",
                               list(overrides))
    return config


def test_swingup_limits_counts_each_ppo_budget_as_its_own_row(tmp_path):
    """The analysis table varies PPO's budget: a run with task.ppo.frames overridden counts in its budget's row
    (the swingup table leaves it out), the same seed at two budgets is two runs, and other overrides stay out."""
    budget = [("task.ppo.frames", 3_000_000), ("task.ppo.eval_episodes", 100)]
    store = ResultStore(tmp_path / "results.sqlite")
    runs = [make_record("true-state", "swingup", 1, {"return_mean": 506.0, "return_std": 1.0},
                        config=resolved("true-state", "swingup")),
            make_record("true-state", "swingup", 1, {"return_mean": 839.0, "return_std": 0.2},
                        config=resolved("true-state", "swingup", budget), created_at="2026-01-03T00:00:00+00:00"),
            make_record("true-state-noisy", "swingup", 0, {"return_mean": 300.0, "return_std": 9.0},
                        config=resolved("true-state-noisy", "swingup", [("encoder.model.noise_std", [0.1] * 5)])),
            make_record("mftcn5", "swingup-probe-state", 0, {"return_mean": 400.0, "return_std": 30.0},
                        config=resolved("mftcn5", "swingup-probe-state")),
            make_record("mftcn1", "swingup-difference", 0, {"return_mean": 520.0, "return_std": 40.0},
                        config=resolved("mftcn1", "swingup-difference")),
            make_record("pve", "swingup", 0, {"return_mean": 315.0, "return_std": 38.0},
                        config=resolved("pve", "swingup"))]
    for run in runs:
        store.put(run)
    text = report(store, ["swingup-limits"])
    assert "506.00 " in line_of(text, "| True state   ", "| 1 M ")
    assert "839.00 (861.41)" in line_of(text, "| True state   ", "| 3 M ")
    assert "400.00 " in line_of(text, "the probe's predicted state", "| 1 M ")
    assert "- (701.30)" in line_of(text, "mfTCN5 e_t", "| 3 M ")
    assert "520.00 " in line_of(text, "mfTCN1 [e_t, e_t - e_t-1]", "| 1 M ")
    assert "| 0 " in line_of(text, "mfTCN1 [e_t, e_t - e_t-1]", "| 3 M ")
    assert "Left out: 1 stored run (1: older spec files or other overrides)" in text  # the other noise
    assert NOT_IN_PAPER not in text and "315.00" not in text  # another encoder's run is the swingup table's
    assert "Not shown: 1 counted run that no row covers (pve on swingup)." in text
    swingup = report(store, ["swingup"])
    assert "506.00 " in line_of(swingup, "True State") and "839.00" not in swingup
    assert "315.00 " in line_of(swingup, "PVE")


def test_the_from_scratch_ablation_is_its_own_probe_row_and_other_overrides_are_labelled():
    """The probe table varies the base: the small-cnn ablation fills its row and never the frozen-base row
    of the same size and lookback; a run with one of those keys overridden alone is a labelled extra row."""
    scratch = [("encoder.model.base.name", "small-cnn"), ("encoder.model.adapter_channels", 0),
               ("encoder.train.lr", 0.0001)]
    runs = [make_record("mftcn4", "cartpole-probe", 0, {"average": 0.6}, config=probe_config("mftcn4")),
            *(make_record("mftcn4", "cartpole-probe", seed, {"average": value},
                          config=resolved("mftcn4", "cartpole-probe", scratch))
              for seed, value in ((0, 3.7), (1, 3.9))),
            make_record("mftcn4", "cartpole-probe", 0, {"average": 5.0},
                        config=resolved("mftcn4", "cartpole-probe", scratch[2:]))]
    rows = {r.labels: r for r in table_rows(TABLES["probe"], runs)}
    assert rows[("32", "4")].seeds == 1 and rows[("32", "4")].stats[0].mean == 0.6
    ablation = rows[("32", "4, from scratch")]
    assert ablation.seeds == 2 and ablation.stats[0].mean == pytest.approx(3.8) and ablation.paper is None
    (extra,) = [r for r in rows.values() if r.labels[0] == NOT_IN_PAPER]
    assert extra.encoder == "mftcn4 (train.lr=0.0001)" and extra.stats[0].mean == 5.0


def test_cheetah_limits_sets_the_difference_input_beside_e_t_and_leaves_other_encoders_to_the_cheetah_table():
    runs = [make_record("mftcn5", "cheetah-difference", seed, {"return_mean": 300.0 + 20 * seed, "return_std": 30.0},
                        config=resolved("mftcn5", "cheetah-difference")) for seed in (0, 1)]
    runs += [make_record("mftcn5", "cheetah", 0, {"return_mean": 280.0, "return_std": 25.0},
                         config=resolved("mftcn5", "cheetah")),
             make_record("random-state", "cheetah", 0, {"return_mean": 55.0, "return_std": 9.0},
                         config=resolved("random-state", "cheetah"))]
    table = TABLES["cheetah-limits"]
    text = render(table, table_rows(table, runs, accept=accept_all))
    difference = line_of(text, "| mfTCN5 [e_t, e_t - e_t-1] ")
    assert "310.00 ± 14.14 " in difference and "| 2 " in difference
    assert "280.00 (360.50)" in line_of(text, "| mfTCN5 e_t ")
    assert "- (390.16)" in line_of(text, "True state")
    assert NOT_IN_PAPER not in text and "55.00" not in text  # random state is the cheetah table's
    assert "310.00" not in render(TABLES["cheetah"], table_rows(TABLES["cheetah"], runs, accept=accept_all))


def test_a_3m_run_counts_in_the_3m_row_only_with_the_papers_test_episodes(tmp_path):
    store = ResultStore(tmp_path / "results.sqlite")
    store.put(make_record("true-state", "swingup", 0, {"return_mean": 820.0, "return_std": 0.2},
                          config=resolved("true-state", "swingup", [("task.ppo.frames", 3_000_000)])))
    text = report(store, ["swingup-limits"])
    assert "- (861.41)" in line_of(text, "| True state   ", "| 3 M ")
    assert "Not shown: 1 counted run that no row covers (true-state (task.ppo.frames=3000000) on swingup)." in text


def test_tables_show_the_paper_presets_runs_before_the_quick_ones_and_name_the_other_presets(tmp_path):
    """Unnamed, a table shows each paper row's paper-preset runs, then its quick ones, the preset labelled;
    runs of other presets (demo, smoke) stay out of it and a line names them and how to show them."""
    store = ResultStore(tmp_path / "results.sqlite")
    for preset, seed, value in (("quick", 0, 480.0), ("quick", 1, 500.0), ("paper", 0, 690.0), ("smoke", 0, 5.0)):
        store.put(make_record("mftcn5", "swingup", seed, {"return_mean": value, "return_std": 30.0}, preset=preset))
    text = report(store, ["swingup"], accept=accept_all)
    rows = [line for line in text.splitlines() if "| mftcn5 " in line and "| swingup " in line]
    assert len(rows) == 2 and "| paper " in rows[0] and "| quick " in rows[1]
    assert "690.00 (701.30)" in rows[0] and "490.00 ± 14.14 (701.30)" in rows[1]
    assert "5.00" not in text
    assert "Not shown: 1 stored run of preset smoke (`report swingup --preset smoke` shows them)." in text
    smoke = report(store, ["swingup"], "smoke", accept=accept_all)
    assert "5.00 (701.30)" in line_of(smoke, "| mftcn5 ", "| swingup ", "| smoke ") and "690.00" not in smoke
    assert "Not shown" not in smoke
