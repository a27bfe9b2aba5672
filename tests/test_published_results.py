"""The run records committed under results/: each must import into a store and name what it ran.

These files are the evidence behind the README's numbers (config, versions, curves of each run), so a
change to the record format or to the registry that would make them unreadable fails here, not on a
researcher's machine. So does a spec change that would drop a published run from the boards (the last
test): rerun that row, or move its record out of results/ and say so in the README.
"""

import json
from pathlib import Path

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
