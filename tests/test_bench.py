"""The benchmark table's logic (targets, rows, alternation, the probe's memory arithmetic) and a small smoke
of `mftcn-bench bench`; speed itself is measured under benchmarks/, never asserted here."""

import json
import math

import numpy as np
import pytest

from mftcn_bench.cli import main
from mftcn_bench.perf import bench_probe, collection, streaming, timing


def row(ratio, target, value=1.0):
    return timing.BenchRow("figure", value, "frames/s", "reference", 2.0, ratio, target)


def test_targets_decide_met_on_the_ratio_or_the_value():
    assert row(10.0, timing.Target(">=", 10)).met is True
    assert row(9.99, timing.Target(">=", 10)).met is False
    assert row(1.5, timing.Target("<=", 1.5)).met is True
    assert row(1.51, timing.Target("<=", 1.5)).met is False
    assert row(None, timing.Target("<=", 4, on="value", unit=" GiB"), value=3.9).met is True
    assert row(None, timing.Target("<=", 4, on="value", unit=" GiB"), value=4.1).met is False
    assert row(1.0, timing.Target("report")).met is None
    assert row(math.nan, timing.Target(">=", 2)).met is None
    assert str(timing.Target(">=", 0.5)) == ">= 0.5x" and str(timing.Target("report")) == "report"


def test_table_has_one_line_per_row_with_every_column():
    rows = [row(12.0, timing.Target(">=", 10)), row(0.06, timing.Target(">=", 0.5)),
            timing.BenchRow("probe", 1.4, "GiB", "-", None, None, timing.Target("<=", 4, on="value", unit=" GiB"))]
    lines = timing.format_table(rows).splitlines()
    assert [c.strip() for c in lines[0].strip("|").split("|")] == ["figure", "value", "reference", "ratio",
                                                                    "target", "met"]
    assert len(lines) == 2 + len(rows)
    assert "12.00x" in lines[2] and "yes" in lines[2]
    assert "0.06x" in lines[3] and "NO" in lines[3]
    assert "1.4 GiB" in lines[4] and "<= 4 GiB" in lines[4] and "yes" in lines[4]


def test_alternate_reverses_the_order_every_other_round_and_reports_work_per_second():
    calls = []

    def block(name, work, seconds):
        def run():
            calls.append(name)
            return work, seconds
        return run

    rates = timing.alternate({"a": block("a", 10, 2.0), "b": block("b", 3, 1.0)}, rounds=3)
    assert calls == ["a", "b", "a", "b", "b", "a", "a", "b"]  # warm-up, then a b / b a / a b
    assert rates == {"a": 5.0, "b": 3.0}


def test_paper_scale_peak_adds_the_embedding_phase_growth_for_the_frames_it_did_not_probe():
    small = bench_probe.ProbeMemory(2000, 1_000_000_000, 500, 296, 1.0, 1.0)
    larger = bench_probe.ProbeMemory(3000, 1_010_000_000, 500, 296, 1.0, 1.0)
    fit = bench_probe.ProbeMemory(180_000, 0, 900_000_000, 296, 0.0, 1.0)
    growth = 10_000_000 / 1000  # measured growth (10 KB a frame) exceeds the features' 296 B
    assert bench_probe.embedding_growth([small, larger]) == growth
    assert bench_probe.paper_scale_peak([small, larger], fit, 180_000) == 1_010_000_000 + 177_000 * growth
    flat = bench_probe.ProbeMemory(3000, 999_000_000, 500, 296, 1.0, 1.0)  # noise: never below the features
    assert bench_probe.paper_scale_peak([small, flat], fit, 180_000) == 999_000_000 + 177_000 * 296
    big_fit = bench_probe.ProbeMemory(180_000, 0, 3_000_000_000, 296, 0.0, 1.0)
    assert bench_probe.paper_scale_peak([small, larger], big_fit, 180_000) == 3_000_000_000


def test_probe_dataset_subset_links_the_chunks_of_the_first_episodes(tmp_path):
    root = bench_probe.write_dataset(tmp_path / "datasets", 3, 1, 5, 8)
    sub = bench_probe.subset(root, 2, 1, tmp_path / "sub")
    manifest = json.loads((sub / "manifest.json").read_text())
    assert [c["split"] for c in manifest["chunks"]] == ["train", "train", "test"]
    from mftcn_bench.data.dataset import MultiViewDataset

    episode = MultiViewDataset(sub).load(manifest["chunks"][0]["episode"])
    assert episode.frames.shape == (2, 5, 8, 8, 3)
    assert np.all(episode.frames[0, 1] == episode.frames[0, 1, 0, 0])  # constant within a frame


def test_probe_embedding_phase_runs_the_task_as_a_run_does(tmp_path, monkeypatch):
    """`measure_embedding` wraps the task's own feature extraction: a change to `CartpoleProbe` that the
    benchmark no longer matches fails here, not only in `mftcn-bench bench`. Like a run, mftcn4 embeds
    from its feature cache: it never runs the base on the probe's frames."""
    import torch

    from mftcn_bench.core.registry import get
    from mftcn_bench.data.cartpole import TARGETS
    from mftcn_bench.encoders import mftcn

    def no_base_pass(*args, **kwargs):
        raise AssertionError("the probe ran the base on frames its feature cache holds")

    monkeypatch.setattr(mftcn, "base_features", no_base_pass)

    threads = torch.get_num_threads()  # measure_embedding pins one thread, as in its child process
    root = bench_probe.write_dataset(tmp_path / "datasets", 2, 1, 30, 32)
    held_before = _status_bytes("VmRSS")
    try:
        memory = bench_probe.measure_embedding(root)
    finally:
        torch.set_num_threads(threads)
    held_after, peak_after = _status_bytes("VmRSS"), _status_bytes("VmHWM")
    assert memory.frames == 90
    # What the probe keeps per frame: [e_t, e_t - e_t-1] in float32, the five float64 targets and the int64
    # episode index of the row; not the frames' pixels, not one split only.
    dim = get("encoders", "mftcn4").spec.embedding_dim
    assert memory.feature_bytes == 2 * dim * 4 + len(TARGETS) * 8 + 8
    # Peaks in bytes (VmHWM is in kB): the embedding phase's is no less than what the process held when it
    # began; the fit phase's (counted from the reset after embedding) is no more than the peak read after
    # it and no less than what the process still held then. The kernel counts RSS in per-CPU batches, so a
    # reading can lag by some pages: a few MiB of slack on the lower bounds.
    slack = 16 * 2**20
    assert memory.embed_peak >= held_before - slack
    assert held_after - slack <= memory.fit_peak <= peak_after
    assert len(list((root.parent / f"{root.name}-home" / "features").glob("*/manifest.json"))) == 1


def _status_bytes(field: str) -> int:
    """A memory figure of this process from /proc/self/status, in bytes."""
    line = next(line for line in open("/proc/self/status") if line.startswith(f"{field}:"))
    return int(line.split()[1]) * 1024


def test_bench_command_prints_and_writes_the_table(tmp_path, capsys):
    out = tmp_path / "perf.md"
    assert main(["bench", "--quick", "--only", "streaming", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "streaming mfTCN step, lookback 29" in printed and "<= 1.3x the cost" in printed
    text = out.read_text()
    assert text.startswith("# mftcn-bench bench (quick)") and "cores" in text and "| figure" in text
    # The row as written agrees with itself: ratio = value / reference (both in ms, 3 significant figures
    # printed, the ratio to 2 decimals), and met is the target applied to the unrounded ratio.
    [line] = [line for line in text.splitlines() if line.startswith("| streaming mfTCN step")]
    _, value, reference, ratio, target, met = (cell.strip() for cell in line.strip("|").split("|"))
    assert value.endswith(" ms") and reference.startswith("lookback 1: ") and reference.endswith(" ms")
    cost, reference_cost = (float(cell.removesuffix(" ms").replace(",", ""))
                            for cell in (value, reference.removeprefix("lookback 1: ")))
    shown = float(ratio.removesuffix("x"))
    assert shown == pytest.approx(cost / reference_cost, rel=0.012, abs=0.006)
    assert target == "<= 1.3x the cost" and met in ("yes", "NO")
    if abs(shown - 1.3) > 0.01:  # away from the rounding of the printed ratio, met is the target's verdict
        assert met == ("yes" if shown < 1.3 else "NO")
    # met is decided on the unrounded ratio, so a shown 1.30x may be either side of the bound.
    if abs(shown - 1.3) > 0.005:
        assert met == ("yes" if shown < 1.3 else "NO")


@pytest.mark.parametrize(("rates", "cost", "reference_cost", "ratio", "met"),
                         [({"29": 50.0, "1": 100.0}, 20.0, 10.0, 2.0, False),
                          ({"29": 100.0, "1": 110.0}, 10.0, 1000 / 110, 1.1, True)])
def test_streaming_row_turns_steps_per_second_into_the_cost_ratio(monkeypatch, rates, cost, reference_cost,
                                                                  ratio, met):
    """Hand-made rates (pushes/s of lookback 29 and of lookback 1): the row is in ms per step, its ratio
    is the longer lookback's cost over the shorter one's (not the ratio of rates, which is its inverse), and
    the target `<= 1.3x` is met or not on that ratio."""

    class Stream:
        def push(self, frame, running):
            raise AssertionError("the rates are given: nothing is pushed")

    monkeypatch.setattr(streaming, "_streamer", lambda frames, stride: (Stream(), None))
    monkeypatch.setattr(streaming, "alternate", lambda blocks, rounds: dict(rates))
    got = streaming.bench_streaming(timing.QUICK)
    assert (got.unit, got.reference) == ("ms", "lookback 1")
    assert got.value == pytest.approx(cost) and got.reference_value == pytest.approx(reference_cost)
    assert got.ratio == pytest.approx(ratio) and got.met is met
    assert got.cells()["met"] == ("yes" if met else "NO") and got.cells()["ratio"] == f"{ratio:.2f}x"


def test_bench_command_refuses_an_unknown_figure(capsys):
    assert main(["bench", "--quick", "--only", "renders"]) == 2
    assert "unknown benchmark(s) ['renders']" in capsys.readouterr().err


def test_image_sized_offscreen_buffer_renders_the_same_pixels():
    """The renderer's speed-up (an offscreen buffer of the image's size, not the suite's 640x480) must not
    change a pixel: datasets keep their checksums."""
    from mftcn_bench.sim.rendering import MultiViewRenderer, RenderSettings, ensure_gl

    ensure_gl()
    from dm_control import suite
    from dm_control.mujoco.engine import Camera

    ours, plain = (suite.load("cartpole", "swingup", task_kwargs={"random": 3}) for _ in range(2))
    settings = RenderSettings(shadowsize=16, offsamples=0, shadows=False, reflection=False)
    renderer = MultiViewRenderer(ours.physics, ["fixed", "lookatcart"], 48, 96, settings)
    plain.physics.model.vis.quality.shadowsize, plain.physics.model.vis.quality.offsamples = 16, 0
    plain.physics.model.light_castshadow[:] = 0
    plain.physics.model.mat_reflectance[:] = 0
    assert (plain.physics.model.vis.global_.offwidth, plain.physics.model.vis.global_.offheight) == (640, 480)
    cameras = [Camera(plain.physics, 48, 96, camera_id=c) for c in ("fixed", "lookatcart")]
    ours.reset()
    plain.reset()
    rng = np.random.default_rng(0)
    for _ in range(5):
        with plain.physics.reset_context():
            plain.physics.set_state(ours.physics.get_state())
        assert np.array_equal(renderer.render(), np.stack([c.render() for c in cameras]))
        ours.step(rng.uniform(-1, 1, 1))


@pytest.mark.parametrize(("stream", "rendered"), [("physics-rate", 5), ("agent-rate", 1)])
def test_the_rendering_only_reference_renders_what_mftcn5_sees_and_embeds_nothing(stream, rendered):
    """The PPO-on-pixels target compares mfTCN5's rollout with the same loop minus the encoder: the same
    environments rendering the same frames per agent step, observations of the same size, all zero. On the
    physics-rate stream a clip reaches the last 5 of 8 physics steps; on the agent-rate stream it is the
    last 5 agent steps, one rendered frame each."""
    import dataclasses

    from mftcn_bench.rl.suite_env import suite_env_of

    sizes = dataclasses.replace(timing.QUICK, ppo_envs=2, ppo_pixel_steps=2)
    task = collection.STREAMS[stream]
    subject, repeat = collection.suite_collector("mftcn5", sizes, sizes.ppo_pixel_steps, task)
    reference, same_repeat = collection.suite_collector("mftcn5", sizes, sizes.ppo_pixel_steps, task, render_only=True)
    try:
        assert repeat == same_repeat == 8
        assert suite_env_of(reference.env).stream_frames == suite_env_of(subject.env).stream_frames == rendered
        observed = next(iter(reference))["observation"]
        assert observed.shape == next(iter(subject))["observation"].shape == (2, 2, 32)
        assert not observed.any()
    finally:
        subject.shutdown()
        reference.shutdown()
