"""Plots: PNG files from synthetic stored runs, and the curve averaging they use."""

import numpy as np
import pytest

from mftcn_bench.results.plots import mean_curve, plot_curves, plot_pouring_lookback, plot_probe_lookback
from tests.records import make_record

PNG = b"\x89PNG\r\n\x1a\n"


def accept_all(record):
    return True


def test_mean_curve_interpolates_onto_the_range_every_seed_covers():
    a = {"frames": [0, 10, 20], "return": [0, 10, 20]}
    b = {"frames": [0, 15], "return": [10, 40]}
    grid, mean, std = mean_curve([a, b])
    assert grid[0] == 0 and grid[-1] == 15
    i = int(np.argmin(abs(grid - 7.5)))
    assert mean[i] == pytest.approx((grid[i] + 10 + 2 * grid[i]) / 2)
    assert std[i] == pytest.approx(np.std([grid[i], 10 + 2 * grid[i]], ddof=1))
    assert mean_curve([a])[2] is None


def test_learning_curves_png(tmp_path):
    runs = [make_record(e, "swingup", s, {"return_mean": 1.0},
                        curves={"train": {"frames": [0, 500, 1000], "wall_s": [0, 1, 2],
                                          "return": [0.0, 100.0 * (s + 1), 300.0]}})
            for e in ("mftcn5", "true-state") for s in range(2)]
    (path,) = plot_curves(runs, tmp_path, accept=accept_all)
    assert path.name == "curves-swingup-quick.png" and path.read_bytes()[:8] == PNG
    assert plot_curves(runs, tmp_path / "none", task="cheetah", accept=accept_all) == []


def test_lookback_plots_png(tmp_path):
    probe = [make_record(f"mftcn{k}", "cartpole-probe", s, {"average": 1.0 / k + s, "position": 0.1, "motion": 2.0},
                         frames=k) for k in (1, 2, 4) for s in range(2)]
    (path,) = plot_probe_lookback(probe, tmp_path, accept=accept_all)
    assert path.name == "probe-lookback-quick.png" and path.read_bytes()[:8] == PNG
    pouring = [make_record(name, "pouring", 0, {"static_error": 20.0, "motion_error": 25.0, "alignment_error": 9.0},
                           frames=frames, stride=stride)
               for name, frames, stride in (("mftcn1", 1, 1), ("mftcn7", 3, 3), ("mftcn13", 4, 4))]
    (path,) = plot_pouring_lookback(pouring, tmp_path, accept=accept_all)
    assert path.name == "pouring-lookback-quick.png" and path.stat().st_size > 1000
