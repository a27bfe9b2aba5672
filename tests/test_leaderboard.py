"""Leaderboards: ranking from the task spec, a pure function of the stored results."""

import dataclasses

import pytest

from mftcn_bench.core import registry
from mftcn_bench.core.specs import TaskSpec, resolve_config
from mftcn_bench.results.leaderboard import entries, render_boards, write_boards
from mftcn_bench.results.ranking import Ranking, ranking
from mftcn_bench.results.selection import shared_dataset
from tests.records import make_record, probe_config

RESULTS = [("true-state", 0, 0.001, "2026-03-01T10:00:00+00:00"), ("true-state", 1, 0.003, "2026-03-04T10:00:00+00:00"),
           ("pve", 0, 2.7, "2026-03-02T10:00:00+00:00"), ("random-state", 0, 4.4, "2026-03-03T10:00:00+00:00")]


def records():
    return [make_record(e, "cartpole-probe", s, {"average": v}, config=probe_config(e), created_at=at)
            for e, s, v, at in RESULTS]


def test_the_leaderboard_table_is_read_from_the_spec_and_is_not_part_of_a_run_config():
    spec = registry.get("tasks", "cartpole-probe").spec
    assert ranking("cartpole-probe") == Ranking("average", False, "Average MSE")
    _, config = resolve_config(registry.get("encoders", "mftcn4").spec, spec, "quick")
    assert "leaderboard" not in config["task"]  # adding it changed no run id
    assert ranking("no-such-task") is None
    with pytest.raises(Exception, match="leaderboard"):
        TaskSpec.from_dict("t", {"description": "d", "default_preset": "p", "presets": {"p": {}},
                                 "leaderboard": {"metric": 3}})


def test_board_ranks_pixel_encoders_and_lists_references_apart():
    text = render_boards(records())["cartpole-probe.md"]
    ranked, references = text.split("References (not ranked):")
    lines = [line for line in ranked.splitlines() if line.startswith("| ") and "rank" not in line]
    assert [[c.strip() for c in line.split("|")[1:-1]] for line in lines] == [
        ["1", "pve", "2.70", "-", "1", "pixels, action", "dataset", "mftcn-bench 0.1.0", "2026-03-02"]]
    lines = [line for line in references.splitlines() if line.startswith("| ") and "role" not in line]
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in lines]
    assert [row[:2] for row in rows] == [["true-state", "reads: state"], ["random-state", "floor (random features)"]]
    assert rows[0][2:] == ["0.00200 ± 0.00141", "-", "2", "dataset", "mftcn-bench 0.1.0", "2026-03-04"]  # 3 digits
    assert "Not one data set" not in text
    assert "## preset `quick`" in text and "ddof=1" in text


def test_an_entry_on_another_recording_than_the_boards_latest_run_is_marked():
    def run(encoder, dataset, at):
        record = make_record(encoder, "cartpole-probe", 0, {"average": 1.0}, config=probe_config(encoder),
                             created_at=at)
        return dataclasses.replace(record, dataset_id=dataset)

    runs = [run("mftcn1", "old0recording000", "2026-03-01T10:00:00+00:00"),
            run("mftcn5", "new0recording000", "2026-03-05T10:00:00+00:00"),
            run("pixels-cnn", None, "2026-03-09T10:00:00+00:00")]  # reads no data: not the board's data set
    board = {e.encoder: e for e in entries(runs, ranking("cartpole-probe"))}
    assert (board["mftcn1"].dataset, board["mftcn1"].other_dataset) == ("old0recording000", True)
    assert (board["mftcn5"].dataset, board["mftcn5"].other_dataset) == ("new0recording000", False)
    assert (board["pixels-cnn"].dataset, board["pixels-cnn"].other_dataset) == (None, False)
    text = render_boards(runs)["cartpole-probe.md"]
    cells = {row[1]: row[6] for row in ([c.strip() for c in line.split("|")[1:-1]]
                                        for line in text.splitlines() if line.startswith("| ") and "rank" not in line)}
    assert cells == {"mftcn1": "old0recording000 *", "mftcn5": "new0recording000", "pixels-cnn": "-"}
    assert "Entries marked * rest on another recording" in text and "runs read new0recording000." in text


def test_the_note_names_the_boards_data_set_when_the_runs_that_read_it_lack_the_ranked_metric():
    def run(encoder, seed, dataset, metrics):
        record = make_record(encoder, "cartpole-probe", seed, metrics, config=probe_config(encoder),
                             created_at=f"2026-03-0{seed + 1}T10:00:00+00:00")
        return dataclasses.replace(record, dataset_id=dataset)

    runs = [run("mftcn5", 0, "new0recording000", {}), run("mftcn5", 1, "new0recording000", {}),
            run("mftcn1", 2, "old0recording000", {"average": 1.0})]
    assert [e.encoder for e in entries(runs, ranking("cartpole-probe"))] == ["mftcn1"]  # mftcn5 has no metric
    text = render_boards(runs)["cartpole-probe.md"]
    assert "old0recording000 *" in text and "Most of this board's runs read new0recording000." in text


def test_the_boards_data_set_is_the_one_most_runs_read_and_a_tie_goes_to_the_latest():
    def run(seed, dataset, at):
        return dataclasses.replace(make_record("mftcn5", "swingup", seed, {}, created_at=at), dataset_id=dataset)

    old, new = "old0recording000", "new0recording000"
    two_old = [run(0, old, "2026-03-01T00:00:00+00:00"), run(1, old, "2026-03-02T00:00:00+00:00"),
               run(2, new, "2026-03-09T00:00:00+00:00"), run(3, None, "2026-03-10T00:00:00+00:00")]
    assert shared_dataset(two_old) == old  # more runs, though older
    assert shared_dataset(two_old[1:]) == new  # one each: the latest
    assert shared_dataset(two_old[3:]) is None  # no run reads data


def test_higher_is_better_reverses_the_order():
    runs = [make_record(e, "t", 0, {"m": v}) for e, v in (("a", 1.0), ("b", 3.0), ("c", 2.0))]
    assert [e.encoder for e in entries(runs, Ranking("m", True, "M"))] == ["b", "c", "a"]
    assert [e.encoder for e in entries(runs, Ranking("m", False, "M"))] == ["a", "c", "b"]


def test_same_results_same_bytes_whatever_the_order(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    write_boards(records(), a)
    write_boards(list(reversed(records())), b)
    names = sorted(p.name for p in a.iterdir())
    assert names == ["README.md", "cartpole-probe.md"]
    assert all((a / n).read_bytes() == (b / n).read_bytes() for n in names)
    index = (a / "README.md").read_text()
    assert "[cartpole-probe](cartpole-probe.md)" in index and "| pve: 2.70 | 1 |" in index


def test_a_board_whose_task_has_no_runs_left_is_removed_and_other_folders_are_left_alone(tmp_path):
    boards, elsewhere = tmp_path / "boards", tmp_path / "notes"
    write_boards(records(), boards)
    (boards / "renamed-task.md").write_text("# renamed-task\n")  # a board of a task since renamed
    write_boards(records(), boards)
    assert sorted(p.name for p in boards.iterdir()) == ["README.md", "cartpole-probe.md"]
    elsewhere.mkdir()
    (elsewhere / "README.md").write_text("# My notes\n")
    (elsewhere / "plan.md").write_text("mine\n")
    write_boards(records(), elsewhere)  # a folder whose index is not ours: nothing of the user's is removed
    assert (elsewhere / "plan.md").read_text() == "mine\n"


def test_iqm_column_from_three_seeds_and_tasks_without_a_board_are_named():
    runs = [make_record("pve", "cartpole-probe", s, {"average": v}, config=probe_config("pve"))
            for s, v in enumerate((1.0, 2.0, 9.0))]
    runs.append(make_record("pve", "unknown-task", 0, {"x": 1.0}))
    files = render_boards(runs, accept=lambda r: True)
    # Three seeds: floor(3 / 4) = 0 values cut from each end, so the IQM is the mean (4.0), said on the board.
    board = " ".join(files["cartpole-probe.md"].split())
    assert "| 4.00 ± 4.36 | 4.00 [1.00, 9.00] |" in board
    assert "nothing is cut" in files["cartpole-probe.md"]
    four = [make_record("pve", "cartpole-probe", s, {"average": v}, config=probe_config("pve"))
            for s, v in enumerate((1.0, 2.0, 3.0, 10.0))]
    four_board = " ".join(render_boards(four, accept=lambda r: True)["cartpole-probe.md"].split())
    assert "| 4.00 ± 4.08 | 2.50 [1.00, 10.0] |" in four_board
    assert "without a board" in files["README.md"] and "unknown-task" in files["README.md"]


def test_a_tasks_boards_put_the_paper_preset_first_then_quick_then_the_others():
    runs = [make_record("mftcn1", "cartpole-probe", 0, {"average": value}, preset=preset)
            for preset, value in (("demo", 3.0), ("quick", 0.5), ("paper", 0.1), ("smoke", 9.0))]
    text = render_boards(runs, accept=lambda r: True)["cartpole-probe.md"]
    headings = [line for line in text.splitlines() if line.startswith("## preset")]
    assert headings == ["## preset `paper`", "## preset `quick`", "## preset `demo`", "## preset `smoke`"]


def _row_of_two(change):
    """Seeds 0 and 1 of one mftcn1 row, seed 1 recorded later with `change` applied to its record."""
    from dataclasses import replace

    code = {"encoder": {"module": "mftcn_bench.encoders.mftcn", "distribution": "mftcn-bench", "version": "0.1.0",
                        "source": "aaaa", "editable": True},
            "task": {"module": "mftcn_bench.tasks.probe", "distribution": "mftcn-bench", "version": "0.1.0",
                     "source": "bbbb", "editable": True}, "harness": "h"}
    first = make_record("mftcn1", "cartpole-probe", 0, {"average": 1.0}, config={**probe_config("mftcn1"),
                                                                                   "code": code})
    second = make_record("mftcn1", "cartpole-probe", 1, {"average": 3.0}, config={**probe_config("mftcn1"),
                                                                                    "code": code},
                         created_at="2026-01-03T03:04:05+00:00")
    return [first, change(replace, second)]


@pytest.mark.parametrize(("change", "reason"), [
    (lambda replace, r: replace(r, config={**r.config, "code": {**r.config["code"], "encoder": {
        **r.config["code"]["encoder"], "source": "cccc"}}}), "a different encoder code"),
    (lambda replace, r: replace(r, dataset_id="another-recording"), "a different data set"),
])
def test_a_row_counts_one_code_and_one_data_set_and_the_footer_says_what_was_left_out(change, reason):
    from mftcn_bench.results.selection import counted_runs

    same = _row_of_two(lambda replace, r: r)
    assert [r.seed for r in counted_runs(same)] == [0, 1]
    mixed = _row_of_two(change)
    assert [r.seed for r in counted_runs(mixed)] == [1]  # the latest run's group: seed 0 differs
    files = render_boards(mixed)
    board = " ".join(files["cartpole-probe.md"].split())
    assert "| 1 | mftcn1 | 3.00 | - | 1 |" in board  # never the mean of the two versions (2.00)
    assert f"1: {reason} from the row's latest runs" in files["README.md"]
    # a harness-only change (the runner's digest) does not split a row
    harness = _row_of_two(lambda replace, r: replace(r, config={**r.config, "code": {**r.config["code"],
                                                                                      "harness": "other"}}))
    assert [r.seed for r in counted_runs(harness)] == [0, 1]
