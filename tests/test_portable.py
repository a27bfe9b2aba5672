"""Portable checkpoints, the file moves: an exported run carries its plan, its folder and its fitted encoder;
an import refuses what would not continue. (The end-to-end continuation is in tests/test_kill_resume.py.)"""

import json

import pytest

from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.home import BenchHome
from mftcn_bench.run.portable import MANIFEST, RunPlan, export_run, import_run, plan_of, write_plan


def unfinished_run(home: BenchHome, encoder_dir: str | None = "mftcn5-abc") -> RunPlan:
    plan = plan_of("r1", [("encoder.embedding_dim", 8), ("task.probe.camera", "lookatcart")], encoder="mftcn5",
                   task="swingup", preset="paper", seed=2, dataset="fp", encoder_dir=encoder_dir)
    run_dir = home.runs / "r1"
    run_dir.mkdir(parents=True)
    (run_dir / "ppo_checkpoint.pt").write_bytes(b"checkpoint")
    (run_dir / ".r1.lock").write_bytes(b"")
    write_plan(run_dir, plan)
    if encoder_dir:
        folder = home.encoders / encoder_dir
        folder.mkdir(parents=True)
        (folder / "model.pt").write_bytes(b"weights")
        (folder / "fit.json").write_text('{"final_loss": 0.1}')
    return plan


def test_export_then_import_moves_the_run_folder_and_its_encoder(tmp_path):
    source, target = BenchHome(tmp_path / "a"), BenchHome(tmp_path / "b")
    plan = unfinished_run(source)
    assert plan.command() == ("mftcn-bench run --encoder mftcn5 --task swingup --preset paper --seed 2 "
                              "--set encoder.embedding_dim=8 --set task.probe.camera=\"lookatcart\"")
    moved = export_run(source, "r1", tmp_path / "out")
    assert moved.folder == tmp_path / "out" / "r1" and json.loads((moved.folder / MANIFEST).read_text())["seed"] == 2
    assert not (moved.folder / "run" / ".r1.lock").exists()  # locks stay with their machine
    back = import_run(target, moved.folder)
    assert back.plan == plan
    assert (target.runs / "r1" / "ppo_checkpoint.pt").read_bytes() == b"checkpoint"
    assert (target.encoders / "mftcn5-abc" / "model.pt").read_bytes() == b"weights"
    with pytest.raises(BenchError, match="already in"):
        import_run(target, moved.folder)


def test_export_refuses_a_finished_run_an_unknown_one_and_one_without_a_plan(tmp_path):
    home = BenchHome(tmp_path / "a")
    with pytest.raises(BenchError, match="no run 'r1'"):
        export_run(home, "r1", tmp_path / "out")
    unfinished_run(home, encoder_dir=None)
    (home.runs / "r1" / "plan.json").unlink()
    with pytest.raises(BenchError, match="still fitting its encoder"):
        export_run(home, "r1", tmp_path / "out")
    (home.runs / "r1" / "result.json").write_text("{}")
    with pytest.raises(BenchError, match="is finished"):
        export_run(home, "r1", tmp_path / "out")


def test_an_import_that_would_load_another_fit_is_refused(tmp_path):
    source, target = BenchHome(tmp_path / "a"), BenchHome(tmp_path / "b")
    unfinished_run(source)
    moved = export_run(source, "r1", tmp_path / "out")
    other = target.encoders / "mftcn5-abc"
    other.mkdir(parents=True)
    (other / "fit.json").write_text('{"final_loss": 0.2}')
    with pytest.raises(BenchError, match="another fit"):
        import_run(target, moved.folder)
    with pytest.raises(BenchError, match="not an exported run"):
        import_run(target, tmp_path)
