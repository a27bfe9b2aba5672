"""End to end: the pouring task on its smoke preset through the command line's main()."""

import pytest

from mftcn_bench.cli import main
from mftcn_bench.data.pouring_labels import MOTION, STATIC
from mftcn_bench.results.store import ResultStore

pytestmark = pytest.mark.slow

METRICS = {"static_error", "motion_error", "alignment_error"} | {
    f"error_{k}" for k in ("contact", "within_distance", "tilt_angle", "liquid_flowing", "has_liquid",
                           "reaching", "receding", "going_up", "coming_down")}


def test_smoke_runs_mftcn1_and_mftcn7_and_shows_an_episode(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MFTCN_BENCH_HOME", str(tmp_path / "home"))
    for encoder in ("mftcn1", "mftcn7"):
        assert main(["run", "--encoder", encoder, "--task", "pouring", "--preset", "smoke", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "| Static (mean)" in out and "| Alignment" in out and "Class balance" in out
    records = ResultStore(tmp_path / "home" / "results.sqlite").query(task="pouring")
    assert sorted(r.encoder for r in records) == ["mftcn1", "mftcn7"]
    for record in records:
        assert set(record.metrics) >= METRICS
        m = record.metrics
        # The summaries are the means of their attributes' errors (a wrong grouping or scale fails here).
        for summary, group in (("static_error", STATIC), ("motion_error", MOTION)):
            parts = [m[f"error_{k}"] for k in group if m[f"error_{k}"] is not None]
            assert m[summary] == pytest.approx(sum(parts) / len(parts))
        assert all(0.0 <= m[name] <= 100.0 for name in METRICS if m[name] is not None)
    assert len(list((tmp_path / "home" / "datasets").glob("pouring-sim-*"))) == 1, "both runs share the dataset"
    assert main(["data", "show", "pouring", "--preset", "smoke", "--no-progress", "--out", str(tmp_path / "show"),
                 "--split", "test", "--episode", "1"]) == 0
    assert (tmp_path / "show" / "pouring-sim-test1.png").stat().st_size > 1000
    assert (tmp_path / "show" / "pouring-sim-test1.mp4").stat().st_size > 1000
