"""A plugin whose encoder needs a fit must give its fit a budget: a `[train]` table without `steps` would skip
every preset's `encoder.train.steps` and fit for nothing, so it is refused before any work."""

from pathlib import Path

from mftcn_bench.cli import main
from tests.plugins import install

ROOT = Path(__file__).resolve().parent.parent
FITTED = """
from mftcn_bench.encoders.baselines import RandomStateEncoder


class Fitted(RandomStateEncoder):
    needs_fit = True

    def fit(self, dataset, budget, progress, workdir):
        return {"steps": float(budget.steps)}
"""


def spec(steps: bool) -> str:
    text = (ROOT / "encoders" / "random-state.toml").read_text()
    return text if steps else "\n".join(line for line in text.splitlines() if not line.startswith("steps ="))


def test_a_fit_without_steps_is_refused_in_one_line_before_any_work(tmp_path, monkeypatch, capsys):
    install(monkeypatch, tmp_path / "plugin", "budgetless", "0.1.0", {"enc": FITTED}, {"budgetless": "enc:Fitted"},
            spec=spec(steps=False))
    home = tmp_path / "home"
    assert main(["run", "--encoder", "budgetless", "--task", "cartpole-probe", "--preset", "smoke",
                 "--home", str(home), "--no-progress"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "warning:" not in line]
    assert len(err) == 1 and "no integer steps" in err[0] and "budgetless" in err[0]
    assert not (home / "datasets").exists() or not any((home / "datasets").iterdir())  # nothing collected
    assert main(["check", "encoder", "budgetless"]) == 2
    captured = capsys.readouterr()
    assert "no integer steps" in captured.out + captured.err
