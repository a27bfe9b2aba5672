"""The run records committed under results/: each must import into a store and name what it ran.

These files are the evidence behind the README's numbers (config, versions, curves of each run), so a
change to the record format or to the registry that would make them unreadable fails here, not on a
researcher's machine. So does a spec change that would drop a published run from the boards (the last
test): rerun that row, or move its record out of results/ and say so in the README.
"""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from mftcn_bench.core import registry
from mftcn_bench.core.provenance import TRACKED_PACKAGES
from mftcn_bench.results.leaderboard import render_boards
from mftcn_bench.results.ranking import ranking
from mftcn_bench.results.records_io import import_results, record_from_json
from mftcn_bench.results.store import ResultStore

RESULTS = Path(__file__).resolve().parent.parent / "results"
FILES = sorted(RESULTS.glob("*.json"))


def test_the_results_folder_holds_run_records():
    assert FILES, f"no run records under {RESULTS}"


@pytest.mark.parametrize("path", FILES, ids=[p.stem for p in FILES])
def test_a_published_record_is_complete(path):
    record = record_from_json(json.loads(path.read_text(encoding="utf-8")), path.name)
    assert record.run_id == path.stem
    registry.get("encoders", record.encoder)  # raises a one-line error when the name is not registered
    registry.get("tasks", record.task)
    metric = ranking(record.task).metric
    assert isinstance(record.metrics[metric], float)
    missing = [name for name in (*TRACKED_PACKAGES, "mftcn-bench", "git_commit") if not record.versions.get(name)]
    assert not missing, f"{path.name}: versions lack {missing}"
    assert record.config["task"] and record.config["encoder"]
    if "ppo" in record.config["task"]:  # control runs store their learning curves
        assert record.curves, f"{path.name}: no learning curves"


def test_the_records_import_and_rank(tmp_path):
    store = ResultStore(tmp_path / "results.sqlite")
    summary = import_results(store, RESULTS)
    assert summary.added == len(FILES)
    boards = render_boards(store.query())
    for record in store.query():
        assert f"| {record.encoder} " in boards[f"{record.task}.md"], record.run_id


@pytest.mark.parametrize("name", ["RESULTS.md", "FINDINGS.md"])
def test_the_results_documents_are_generated_from_these_records(capsys, name):
    """docs/RESULTS.md's and docs/FINDINGS.md's tables are exactly what `mftcn-bench results doc` renders from
    results/."""
    from mftcn_bench.cli import main

    document = RESULTS.parent / "docs" / name
    code = main(["results", "doc", str(document), "--records", str(RESULTS), "--check"])
    assert code == 0, capsys.readouterr().err


# --- The printed figures recomputed from the records, without the harness's selection or statistics ---------

# The PPO budget of each preset, as docs/RESULTS.md states it ("paper": 3 M PPO frames and 100 test episodes;
# "quick": 1 M frames on swing-up, 20 test episodes; cheetah keeps 3 M frames at quick, tasks/cheetah.toml).
# A run of another budget (a PPO-limit analysis run with `--set task.ppo.frames=...`) belongs to no row here.
_BUDGETS = {("swingup", "paper"): (3_000_000, 100), ("swingup", "quick"): (1_000_000, 20),
            ("cheetah", "paper"): (3_000_000, 100), ("cheetah", "quick"): (3_000_000, 20)}
_RETURN_TABLES = {"swingup": ("swingup", "swingup-160", "swingup-moving"), "cheetah": ("cheetah",)}
_CELL = re.compile(r"^(?P<mean>-?\d+\.\d+)(?: ± (?P<std>\d+\.\d+))?(?: \((?P<paper>-|-?\d+\.\d+)\))?$")


def _budget(task: str, preset: str) -> tuple[int, int]:
    return _BUDGETS["cheetah" if task == "cheetah" else "swingup", preset]


def _generated_block(text: str, command: str) -> str:
    start = text.index(f"<!-- generated: {command} -->")
    return text[start:text.index("<!-- end generated -->", start)]


def _markdown_rows(block: str) -> list[dict[str, str]]:
    """The rows of the block's one markdown table, as {header: cell}."""
    lines = [line for line in block.splitlines() if line.startswith("|")]
    headers = [cell.strip() for cell in lines[0].strip("|").split("|")]
    return [dict(zip(headers, (cell.strip() for cell in line.strip("|").split("|")), strict=True))
            for line in lines[2:]]


def _row_runs(raw: list[dict], encoder: str, task: str, preset: str) -> list[dict]:
    """The records a row stands for, chosen here by the rule the documents state: the row's encoder, task and
    preset at the preset's PPO budget; of those, the runs on the data set of the newest one (a row never mixes
    two recordings), the latest run per seed."""
    frames, episodes = _budget(task, preset)
    runs = [r for r in raw if (r["encoder"], r["task"], r["preset"]) == (encoder, task, preset)
            and r["config"]["task"]["ppo"]["frames"] == frames
            and r["config"]["task"]["ppo"]["eval_episodes"] == episodes]
    if not runs:
        return []
    newest = max(runs, key=lambda r: r["created_at"])
    latest: dict[int, dict] = {}
    for r in sorted(runs, key=lambda r: r["created_at"]):
        if r.get("dataset_id") == newest.get("dataset_id"):
            latest[r["seed"]] = r
    return list(latest.values())


def _check_cell(cell: str, values: list[float], where: str) -> None:
    """`mean ± std` to 2 decimals: numpy's mean and sample std (ddof=1) of `values`; `mean` alone for one seed."""
    match = _CELL.match(cell)
    assert match, f"{where}: cell {cell!r} is not 'mean ± std (paper)'"
    mean = float(np.mean(values))
    assert abs(float(match["mean"]) - mean) <= 0.005 + 1e-9, f"{where}: printed mean {match['mean']}, records {mean}"
    if len(values) == 1:
        assert match["std"] is None, f"{where}: one seed has no std, printed {cell!r}"
        return
    std = float(np.std(values, ddof=1))
    assert match["std"] is not None and abs(float(match["std"]) - std) <= 0.005 + 1e-9, (
        f"{where}: printed std {match['std']}, the records' sample std (ddof=1) {std}")


def check_return_table(block: str, table: str, raw: list[dict]) -> int:
    """Every row of a return table (`report swingup` / `report cheetah`) against the records it stands for:
    the seed count, then Mean (the runs' mean test return) and Std. (the runs' std over test episodes), each
    as mean ± sample std over seeds; each run's metrics are first recomputed from its stored test-episode
    returns. Every run the rule selects is on a row. Returns the number of rows with runs."""
    tasks = _RETURN_TABLES[table]
    checked: set[tuple[str, str, str]] = set()
    rows = _markdown_rows(block)
    # The data set rows of one task and preset are compared on: the one most of their runs read, a tie going
    # to the latest run's; a row on another is marked `*` after its seed count.
    reading: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        task = row.get("task", tasks[0])
        reading.setdefault((task, row["preset"]), []).extend(
            r for r in _row_runs(raw, row["encoder"], task, row["preset"]) if r.get("dataset_id"))
    shared = {key: max(runs, key=lambda r: (sum(o["dataset_id"] == r["dataset_id"] for o in runs),
                                            r["created_at"], r["run_id"]))["dataset_id"]
              for key, runs in reading.items() if runs}
    for row in rows:
        encoder, task, preset = row["encoder"], row.get("task", tasks[0]), row["preset"]
        where = f"{table} row {encoder} / {task} / {preset}"
        if row["seeds"] == "0":  # a paper row without runs: none of its runs exists at a table preset
            assert preset == "-" and not any(_row_runs(raw, encoder, task, p) for p in ("paper", "quick")), where
            continue
        runs = _row_runs(raw, encoder, task, preset)
        seeds, _, mark = row["seeds"].partition(" ")
        assert int(seeds) == len(runs) == len({r["seed"] for r in runs}), (
            f"{where}: {row['seeds']} seeds printed, {len(runs)} records")
        other = bool(runs[0].get("dataset_id")) and runs[0]["dataset_id"] != shared[task, preset]
        assert mark == ("*" if other else ""), f"{where}: marked {mark!r}, its data set {runs[0].get('dataset_id')}"
        for r in runs:  # the run's own figures, from its test episodes (sample std over episodes)
            returns = r["curves"]["test"]["return"]
            assert len(returns) == r["metrics"]["episodes"] == r["config"]["task"]["ppo"]["eval_episodes"]
            assert r["metrics"]["return_mean"] == pytest.approx(np.mean(returns), rel=1e-9), r["run_id"]
            assert r["metrics"]["return_std"] == pytest.approx(np.std(returns, ddof=1), rel=1e-9), r["run_id"]
        _check_cell(row["Mean"], [np.mean(r["curves"]["test"]["return"]) for r in runs], f"{where}, Mean")
        _check_cell(row["Std."], [np.std(r["curves"]["test"]["return"], ddof=1) for r in runs], f"{where}, Std.")
        checked.add((encoder, task, preset))
    selected = {(r["encoder"], r["task"], r["preset"]) for r in raw
                if r["task"] in tasks and r["preset"] in ("paper", "quick")
                and _row_runs(raw, r["encoder"], r["task"], r["preset"])}
    assert selected == checked, f"{table}: runs on no row {sorted(selected - checked)}"
    return len(checked)


@pytest.mark.parametrize("table", sorted(_RETURN_TABLES))
def test_the_return_tables_figures_are_numpys_mean_and_sample_std_over_the_records(table):
    """docs/RESULTS.md's swing-up and cheetah tables (paper Tables 2 and 3) recomputed from the JSON records in
    results/ with numpy alone: each row's seed count, and its Mean and Std. cells as numpy's mean ± sample std
    (ddof=1) over the row's runs of the per-run mean and std of the stored test-episode returns, to the printed
    2 decimals. The rows' runs are chosen here by the documents' stated rule (the preset's PPO budget, one
    data set, the latest run per seed), so a population std, a run of another budget or data set mixed in, a
    dropped seed or a run left off the table fails here even when the harness's regeneration agrees."""
    raw = [json.loads(path.read_text(encoding="utf-8")) for path in FILES]
    block = _generated_block((RESULTS.parent / "docs" / "RESULTS.md").read_text(encoding="utf-8"), f"report {table}")
    # Every selected run is on a checked row (check_return_table); rows without runs (a row being rerun) are not.
    assert check_return_table(block, table, raw) > 0
