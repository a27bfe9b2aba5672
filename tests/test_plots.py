"""Plots: the figures drawn from synthetic stored runs (their series, labels and data), the PNG files they
are written to, and the curve averaging they use."""

import numpy as np
import pytest
from matplotlib.colors import to_rgb

from mftcn_bench.results import plots
from mftcn_bench.results.paper_tables import PROBE
from mftcn_bench.results.plots import mean_curve, plot_curves, plot_pouring_lookback, plot_probe_lookback
from tests.records import make_record

PNG = b"\x89PNG\r\n\x1a\n"


def accept_all(record):
    return True


@pytest.fixture
def drawn(monkeypatch):
    """The figures the plot functions save, kept for inspection (each is still written and closed)."""
    figures = []
    save = plots.save_figure

    def keeping(fig, path):
        figures.append(fig)
        return save(fig, path)

    monkeypatch.setattr(plots, "save_figure", keeping)
    return figures


def errorbars(ax) -> dict[str, tuple[list[float], list[float], list[float]]]:
    """label -> (x, y, half the error bar's length) of each errorbar series of `ax`."""
    out = {}
    for container in ax.containers:
        line, _, (bars, *_) = container.lines
        half = [(top[1] - bottom[1]) / 2 for bottom, top in bars.get_segments()]
        out[container.get_label()] = (list(line.get_xdata()), list(line.get_ydata()), half)
    return out


def test_mean_curve_interpolates_onto_the_range_every_seed_covers():
    a = {"frames": [0, 10, 20], "return": [0, 10, 20]}
    b = {"frames": [0, 15], "return": [10, 40]}
    grid, mean, std = mean_curve([a, b])
    assert grid[0] == 0 and grid[-1] == 15
    i = int(np.argmin(abs(grid - 7.5)))
    assert mean[i] == pytest.approx((grid[i] + 10 + 2 * grid[i]) / 2)
    assert std[i] == pytest.approx(np.std([grid[i], 10 + 2 * grid[i]], ddof=1))
    assert mean_curve([a])[2] is None


def test_learning_curves_draw_one_mean_line_and_band_per_encoder(tmp_path, drawn):
    frames = [0, 500, 1000]
    scale = {"mftcn1": 2.0, "mftcn5": 1.0}  # so that the two encoders' lines differ

    def returns(encoder, seed):
        return [0.0, 100.0 * (seed + 1) * scale[encoder], 300.0 * scale[encoder]]

    runs = [make_record(e, "swingup", s, {"return_mean": 1.0},
                        curves={"train": {"frames": frames, "wall_s": [0, 1, 2], "return": returns(e, s)}})
            for e in scale for s in range(2)]
    (path,) = plot_curves(runs, tmp_path, accept=accept_all)
    assert path.name == "curves-swingup-quick.png" and path.read_bytes()[:8] == PNG
    [fig] = drawn
    [ax] = fig.axes
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("environment frames", "episode return (training)")
    assert [line.get_label() for line in ax.lines] == ["mftcn1 (n=2)", "mftcn5 (n=2)"]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["mftcn1 (n=2)", "mftcn5 (n=2)"]
    assert len(ax.collections) == 2  # one ±1 std band per line
    for line, band, encoder in zip(ax.lines, ax.collections, scale, strict=True):
        x = np.asarray(line.get_xdata())
        seeds = np.stack([np.interp(x, frames, returns(encoder, s)) for s in range(2)])
        assert x[0] == 0 and x[-1] == 1000 and len(x) == plots.GRID_POINTS
        assert np.allclose(line.get_ydata(), seeds.mean(0))  # the mean over seeds, not one seed
        # The band spans mean ± the seeds' sample std at each grid point, in the line's colour.
        vertices = band.get_paths()[0].vertices
        middle = len(x) // 3
        at = np.sort(vertices[np.isclose(vertices[:, 0], x[middle]), 1])
        std = seeds.std(0, ddof=1)[middle]
        assert std > 0 and np.allclose([at[0], at[-1]], [seeds.mean(0)[middle] - std, seeds.mean(0)[middle] + std])
        assert np.allclose(band.get_facecolor()[0][:3], to_rgb(line.get_color()))
    assert plot_curves(runs, tmp_path / "none", task="cheetah", accept=accept_all) == []


def test_probe_lookback_plot_draws_the_seed_means_and_the_papers_figures(tmp_path, drawn):
    probe = [make_record(f"mftcn{k}", "cartpole-probe", s, {"average": 1.0 / k + s, "position": 0.1, "motion": 2.0},
                         frames=k) for k in (1, 2, 4) for s in range(2)]
    (path,) = plot_probe_lookback(probe, tmp_path, accept=accept_all)
    assert path.name == "probe-lookback-quick.png" and path.read_bytes()[:8] == PNG
    [fig] = drawn
    axes = {ax.get_title(): ax for ax in fig.axes}
    assert list(axes) == ["average", "position", "motion"]  # one panel per metric
    assert all(ax.get_yscale() == "log" and ax.get_xlabel() == "lookback (frames)" for ax in axes.values())
    # Lookback = (frames - 1) x stride + 1 (stride 1 here); mean and sample std over the two seeds.
    spread = np.std([0.0, 1.0], ddof=1)
    expected = {"average": ([1, 2, 4], pytest.approx([1.5, 1.0, 0.75]), pytest.approx([spread] * 3)),
                "position": ([1, 2, 4], pytest.approx([0.1] * 3), pytest.approx([0.0] * 3)),
                "motion": ([1, 2, 4], pytest.approx([2.0] * 3), pytest.approx([0.0] * 3))}
    for metric, ax in axes.items():
        assert errorbars(ax) == {"ours": expected[metric]}
    # Beside each, dashed in the same colour, the paper's figures for the same embedding size (32).
    paper = {metric: {int(row.labels[1]): row.paper[i] for row in PROBE.rows
                      if row.labels[0] == "32" and row.labels[1].isdigit()}
             for i, metric in enumerate(("average", "position", "motion"))}
    for metric, points in paper.items():
        [line] = [line for line in axes[metric].lines if line.get_linestyle() == "--"]
        assert line.get_label() == "paper" and line.get_color() == axes[metric].containers[0].lines[0].get_color()
        assert list(line.get_xdata()) == sorted(points)
        assert list(line.get_ydata()) == [points[k] for k in sorted(points)]


def test_pouring_lookback_plot_draws_each_error_against_the_clips_lookback(tmp_path, drawn):
    encoders = (("mftcn1", 1, 1), ("mftcn7", 3, 3), ("mftcn13", 4, 4))  # lookbacks 1, 7 and 13
    pouring = [make_record(name, "pouring", 0, {"static_error": 20.0 + frames, "motion_error": 25.0,
                                                "alignment_error": 9.0 - frames},
                           frames=frames, stride=stride)
               for name, frames, stride in encoders]
    (path,) = plot_pouring_lookback(pouring, tmp_path, accept=accept_all)
    assert path.name == "pouring-lookback-quick.png" and path.read_bytes()[:8] == PNG
    [fig] = drawn
    axes = {ax.get_title(): ax for ax in fig.axes}
    assert fig.axes[0].get_yscale() == "linear" and fig.axes[0].get_ylabel() == "error (%)"
    expected = {  # one seed each: no error bar
        "static_error": ([1, 7, 13], pytest.approx([21.0, 23.0, 24.0]), pytest.approx([0.0] * 3)),
        "motion_error": ([1, 7, 13], pytest.approx([25.0] * 3), pytest.approx([0.0] * 3)),
        "alignment_error": ([1, 7, 13], pytest.approx([8.0, 6.0, 5.0]), pytest.approx([0.0] * 3))}
    assert {metric: errorbars(ax)["ours"] for metric, ax in axes.items()} == expected
    # The paper's mfTCN^1/7/13/29 (on the real data set), dashed, beside each error.
    static = [line for line in axes["static_error"].lines if line.get_linestyle() == "--"]
    assert [(list(line.get_xdata()), list(line.get_ydata())) for line in static] == \
        [([1, 7, 13, 29], [18.9, 17.3, 16.8, 19.4])]


def test_plot_reads_a_folder_of_records_and_refuses_a_missing_one(tmp_path, capsys):
    from mftcn_bench.cli import main
    from mftcn_bench.core import registry
    from mftcn_bench.core.specs import resolve_config
    from mftcn_bench.results.records_io import export_results
    from mftcn_bench.results.store import ResultStore

    store = ResultStore(tmp_path / "results.sqlite")
    _, config = resolve_config(registry.get("encoders", "true-state").spec, registry.get("tasks", "swingup").spec,
                               "quick")  # a run of today's specs: the default selection counts it
    for seed in range(2):
        store.put(make_record("true-state", "swingup", seed, {"return_mean": 1.0}, config=config,
                              curves={"train": {"frames": [0, 500, 1000], "wall_s": [0, 1, 2],
                                                "return": [0.0, 1.0, 2.0]}}))
    export_results(store, tmp_path / "records")
    assert main(["plot", "curves", "--records", str(tmp_path / "records"), "--out", str(tmp_path / "png"),
                 "--home", str(tmp_path / "empty-home")]) == 0
    assert (tmp_path / "png" / "curves-swingup-quick.png").read_bytes()[:8] == PNG
    assert main(["plot", "curves", "--records", str(tmp_path / "nothing"), "--home", str(tmp_path / "h")]) == 2
    assert capsys.readouterr().err.strip().endswith(f"records folder {tmp_path / 'nothing'} does not exist; give a "
                                                    f"folder of run JSON files, such as results")
