"""Results export and import: one JSON file per run, a lossless and idempotent round trip."""

import json
from dataclasses import asdict

import pytest

from mftcn_bench.cli import main
from mftcn_bench.results.records_io import ResultsFileError, export_results, import_results
from mftcn_bench.results.store import ResultStore
from tests.records import make_record

CURVES = {"train": {"frames": [0.0, 1000.0], "wall_s": [0.0, 2.5], "return": [10.0, 50.0]}}


@pytest.fixture
def source(tmp_path):
    store = ResultStore(tmp_path / "source.sqlite")
    store.put(make_record("mftcn5", "swingup", 0, {"return_mean": 700.0, "episodes": 10}, curves=CURVES))
    store.put(make_record("pve", "swingup", 1, {"return_mean": 400.0, "nothing": None}))
    return store


def test_round_trip_keeps_every_field(source, tmp_path):
    assert export_results(source, tmp_path / "out") == 2
    files = sorted((tmp_path / "out").glob("*.json"))
    assert {f.stem for f in files} == {r.run_id for r in source.query()}
    target = ResultStore(tmp_path / "target.sqlite")
    summary = import_results(target, tmp_path / "out")
    assert (summary.added, summary.updated, summary.unchanged) == (2, 0, 0)
    assert [asdict(r) for r in target.query()] == [asdict(r) for r in source.query()]
    assert target.query(encoder="mftcn5")[0].curves == CURVES
    again = import_results(target, tmp_path / "out")  # idempotent
    assert (again.added, again.updated, again.unchanged) == (0, 0, 2) and len(target.query()) == 2


def test_a_later_run_of_the_same_id_replaces_the_stored_one(source, tmp_path):
    export_results(source, tmp_path / "out")
    path = next((tmp_path / "out").glob("*.json"))
    data = json.loads(path.read_text())
    data["created_at"] = "2027-01-01T00:00:00+00:00"
    data["metrics"]["return_mean"] = 1.0
    path.write_text(json.dumps(data))
    assert import_results(source, tmp_path / "out").updated == 1
    assert source.get(data["run_id"]).metrics["return_mean"] == 1.0


@pytest.mark.parametrize("change, message", [
    (lambda d: d.pop("metrics"), "missing field 'metrics'"),
    (lambda d: d.update(seed="0"), "field 'seed' has the wrong type"),
    (lambda d: d.update(extra=1), r"unknown fields \['extra'\]"),
])
def test_a_malformed_file_is_named_and_nothing_is_written(source, tmp_path, change, message):
    export_results(source, tmp_path / "out")
    bad = sorted((tmp_path / "out").glob("*.json"))[-1]
    data = json.loads(bad.read_text())
    change(data)
    bad.write_text(json.dumps(data))
    target = ResultStore(tmp_path / "target.sqlite")
    with pytest.raises(ResultsFileError, match=message) as err:
        import_results(target, tmp_path / "out")
    assert bad.name in str(err.value) and target.query() == []


def test_cli_export_import_and_one_line_error(source, tmp_path, monkeypatch, capsys):
    home = tmp_path / "home"
    monkeypatch.setenv("MFTCN_BENCH_HOME", str(home))
    export_results(source, tmp_path / "out")
    assert main(["results", "import", str(tmp_path / "out")]) == 0
    assert "2 added" in capsys.readouterr().out
    assert main(["results", "export", str(tmp_path / "again"), "--task", "swingup"]) == 0
    assert len(list((tmp_path / "again").glob("*.json"))) == 2
    (tmp_path / "out" / "broken.json").write_text("{not json")
    assert main(["results", "import", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "broken.json" in err[0] and "not readable JSON" in err[0]
