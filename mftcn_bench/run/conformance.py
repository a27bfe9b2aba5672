"""`mftcn-bench check encoder NAME`: the encoder contract, run against any registered encoder.

On a small synthetic dataset (textured frames that encode view, episode and time; nothing is rendered)
shaped like the cartpole-probe smoke preset's, with the encoder's config for that preset, it checks what
the harness relies on and a wrong implementation would get past silently: the spec loads, the class
satisfies `Encoder`, its metadata matches the spec, a short fit returns statistics, embeddings have the
right shape, dtype and finite values, `embed_episode` and the rollout path (`streaming`, or the clip window
over `embed`) give `embed`'s embeddings of the same clips (within `TOLERANCE`), a second instance with the
same seed gives the same embeddings, the fit's weights do not depend on the test episodes, a fit killed half-way
and started again ends as an uninterrupted one, a save / load round trip keeps them, what privileged inputs it declares
(the fit and every embedding path then withhold the rest, as a run does), and (`--device`) the saved
encoder placed on a device (`to_device`) embeds as on the CPU. One line per check.
"""

from __future__ import annotations

import tempfile
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mftcn_bench.core import registry
from mftcn_bench.core.device import DevicePlaced, full_float32, resolve_device
from mftcn_bench.core.errors import BenchError
from mftcn_bench.core.home import BenchHome
from mftcn_bench.data.dataset import MultiViewDataset, ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector
from mftcn_bench.encoders.base import (
    ClipBatch,
    Encoder,
    EncoderInfo,
    EpisodeEmbedder,
    StreamingEncoder,
    check_embeddings,
    embed_clips_of_episode,
    embed_episode,
    fit_budget,
    uses_pixels,
)
from mftcn_bench.encoders.privileged import dataset_for, declared_inputs, is_reference, visible
from mftcn_bench.run.artifacts import attach_feature_cache
from mftcn_bench.run.construct import construct_encoder
from mftcn_bench.run.plan import PreparedRun, RunRequest, prepare

# Two paths to the same embedding may differ by TOLERANCE times the embeddings' largest magnitude (at least
# 1): batch size changes the order of float32 sums in convolutions.
TOLERANCE = 1e-5
DEVICE_TOLERANCE = 1e-3  # a GPU against the CPU in full float32: other kernels, other orders of sums
TASK, PRESET = "cartpole-probe", "smoke"  # the dataset shape and the encoder's (small) training budget


@dataclass(frozen=True)
class CheckLine:
    """One check's outcome: `ok`, `FAIL` or `skip`, its name and what was measured or went wrong."""

    status: str
    name: str
    detail: str

    def __str__(self) -> str:
        return f"{self.status:<4}  {self.name:<14}  {self.detail}"


class _Failed(Exception):
    pass


class _Killed(BaseException):
    """Raised from a fit's progress callback to stop it as a killed process would (not an `Exception`, so a
    plugin's own `except Exception` cannot swallow it)."""


def _other_test_episodes(config: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
    """The check's synthetic episodes, with every episode past the train split replaced (frames inverted,
    state negated, actions reversed): the same train split, another test split."""
    arrays = synthetic_collector(config, index)
    if index >= int(config["train_episodes"]):
        arrays = {"frames": 255 - arrays["frames"], "state": -arrays["state"], "action": arrays["action"][::-1]}
    return arrays


def _max_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a.astype(np.float64) - b.astype(np.float64)))) if a.size else 0.0


def _same(a: np.ndarray, b: np.ndarray, what: str, tolerance: float = TOLERANCE) -> str:
    if a.shape != b.shape:
        raise _Failed(f"{what}: shapes {a.shape} and {b.shape} differ")
    diff, bound = _max_diff(a, b), tolerance * max(1.0, float(np.max(np.abs(b), initial=0.0)))
    if not diff <= bound:
        raise _Failed(f"{what}: max |difference| {diff:.3g} > {bound:.3g}")
    return f"{what}: max |difference| {diff:.2g} (allowed {bound:.2g})"


class EncoderCheck:
    """The checks of one registered encoder, run in order in a scratch folder."""

    def __init__(self, name: str, workdir: Path, overrides: Sequence[tuple[str, Any]] = (),
                 device: str = "cpu") -> None:
        self.name, self.workdir = name, workdir
        self.overrides = tuple(overrides)
        self.placement = resolve_device(device)  # refused (one line) before any check runs
        self.home = BenchHome(workdir / "home")
        self.prepared: PreparedRun | None = None
        self.dataset: MultiViewDataset | None = None
        self.encoder: Encoder | None = None

    def _new(self) -> Encoder:
        assert self.prepared is not None and self.dataset is not None
        return construct_encoder(self.prepared.encoder_entry, self.prepared.config["encoder"],
                                 self.prepared.request.seed, self.dataset.image_shape)

    def _fit(self, encoder: Encoder, folder: str, dataset: MultiViewDataset | None = None,
             progress: Callable[..., None] | None = None) -> dict[str, float]:
        assert self.prepared is not None and self.dataset is not None
        dataset = dataset or self.dataset
        attach_feature_cache(encoder, dataset, self.home, show_progress=False)
        if not encoder.needs_fit:
            return {}
        calls: list[tuple] = []

        def record(*args: Any) -> None:
            calls.append(args)
            if progress is not None:
                progress(*args)

        budget = fit_budget(encoder.info.name, self.prepared.config["encoder"].get("train", {}))
        stats = encoder.fit(dataset_for(encoder, dataset), budget, record, self.workdir / folder)
        if not isinstance(stats, dict) or not all(isinstance(v, int | float) for v in stats.values()):
            raise _Failed(f"fit returned {type(stats).__name__} {stats!r:.80}; expected a dict of floats")
        if calls and not (isinstance(calls[-1][0], int) and isinstance(calls[-1][1], int)
                          and isinstance(calls[-1][2], dict)):
            raise _Failed(f"progress was called as {calls[-1]!r:.80}; expected (step, total, {{name: value}})")
        return stats

    def _fit_at(self, encoder: Encoder, size: tuple[int, int]) -> None:
        """Fit `encoder` on the check's synthetic data set drawn at `size` (height, width)."""
        assert self.dataset is not None and self.prepared is not None
        config = {**self.dataset.config, "height": size[0], "width": size[1],
                  "name": f"conformance-{size[0]}x{size[1]}"}
        dataset = ensure_dataset(self.home.datasets, config, synthetic_collector, show_progress=False)
        attach_feature_cache(encoder, dataset, self.home, show_progress=False)
        budget = fit_budget(encoder.info.name, self.prepared.config["encoder"].get("train", {}))
        encoder.fit(dataset_for(encoder, dataset), budget, lambda *a: None, self.workdir / f"fit-{size[0]}x{size[1]}")

    def _episodes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        assert self.dataset is not None
        view = 0
        return [(e.frames[view], e.state) for e in self.dataset.iter_episodes("test")]

    # -- the checks, in order ---------------------------------------------------------------------------

    def spec(self) -> str:
        self.prepared = prepare(RunRequest(self.name, TASK, PRESET, 0, self.overrides, device="cpu"))
        config = {**self.prepared.task.dataset_config, "name": "conformance", "pattern": "gradient"}
        self.dataset = ensure_dataset(self.home.datasets, config, synthetic_collector, show_progress=False)
        entry = self.prepared.encoder_entry
        return f"{entry.entry_point.value}; config of preset {TASK}/{PRESET}"

    def construct(self) -> str:
        self.encoder = self._new()
        return f"{type(self.encoder).__name__} satisfies Encoder"

    def privileged(self) -> str:
        assert self.encoder is not None
        declared = declared_inputs(self.encoder)
        if not declared:
            return "declares no privileged input: pixels only (the true state and actions are withheld)"
        role = ("a reference, ranked apart from the pixel encoders" if is_reference(declared)
                else "ranked with the pixel encoders, its entries marked")
        return f"declares privileged_inputs {list(declared)}: {role}"

    def metadata(self) -> str:
        assert self.encoder is not None and self.prepared is not None and self.dataset is not None
        info, spec = self.encoder.info, self.prepared.config["encoder"]
        if not isinstance(info, EncoderInfo):
            raise _Failed(f"info is a {type(info).__name__}, not an EncoderInfo")
        expected = {"name": self.name, "frames": spec.get("frames", 1), "stride": spec.get("stride", 1),
                    "embedding_dim": spec["embedding_dim"], "image_shape": tuple(self.dataset.image_shape)}
        wrong = [f"{k} {getattr(info, k)!r} (spec: {v!r})" for k, v in expected.items()
                 if (tuple(getattr(info, k)) if k == "image_shape" else getattr(info, k)) != v]
        if wrong:
            raise _Failed("info disagrees with the spec: " + ", ".join(wrong))
        if not isinstance(info.parameter_count, int) or info.parameter_count < 0:
            raise _Failed(f"parameter_count {info.parameter_count!r} is not an int >= 0")
        return (f"{info.frames} frames at stride {info.stride}, {info.embedding_dim}-d, image (H, W) "
                f"{info.image_shape}, {info.parameter_count:,} parameters")

    def fit(self) -> str:
        assert self.encoder is not None
        stats = self._fit(self.encoder, "fit-a")
        if not self.encoder.needs_fit:
            return "needs_fit is False: nothing trained"
        return "returned " + (", ".join(f"{k}={v:.4g}" for k, v in list(stats.items())[:3]) or "{}")

    def embed(self) -> str:
        assert self.encoder is not None
        frames, state = self._episodes()[0]
        reference = embed_clips_of_episode(self.encoder, frames, state)
        check_embeddings(self.encoder, reference, len(frames))
        return f"float32 {reference.shape}, finite, over every clip of a {len(frames)}-frame episode"

    def embed_episode(self) -> str:
        assert self.encoder is not None
        if not isinstance(self.encoder, EpisodeEmbedder):
            return "not provided: the harness builds every clip and calls embed"
        lines = []
        for frames, state in self._episodes():
            lines.append(_same(embed_episode(self.encoder, frames, state),
                               embed_clips_of_episode(self.encoder, frames, state), "vs embed"))
        return lines[-1] + f" ({len(lines)} episodes)"

    def streaming(self) -> str:
        """Two environments fed frame by frame, the second restarting mid-way: each step's output is the
        embedding of the clip ending there."""
        from mftcn_bench.rl.observers import make_observer

        assert self.encoder is not None
        (a_frames, a_state), (b_frames, b_state) = self._episodes()[:2]
        half = len(b_frames) // 2
        pixels = uses_pixels(self.encoder)
        observer = make_observer(self.encoder, 2)
        got, want = [], []
        ref_a = embed_clips_of_episode(self.encoder, a_frames, a_state)
        ref_b1 = embed_clips_of_episode(self.encoder, b_frames[:half], b_state[:half])
        ref_b2 = embed_clips_of_episode(self.encoder, b_frames[half:], b_state[half:])
        for t in range(len(a_frames)):
            tb = t if t < half else t - half
            b_f, b_s = (b_frames, b_state) if t < half else (b_frames[half:], b_state[half:])
            frames = np.stack([a_frames[t], b_f[tb]]) if pixels else None
            start = np.array([t == 0, t == 0 or t == half])
            out = observer.push(frames, start, np.stack([a_state[t], b_s[tb]]))
            got.append(out)
            want.append(np.stack([ref_a[t], (ref_b1 if t < half else ref_b2)[tb]]))
        how = "streaming()" if isinstance(self.encoder, StreamingEncoder) else "clip window over embed"
        return _same(np.stack(got), np.stack(want), f"{how} vs embed, 2 environments, a restart")

    def determinism(self) -> str:
        assert self.encoder is not None
        twin = self._new()
        self._fit(twin, "fit-b")
        frames, state = self._episodes()[0]
        return _same(embed_clips_of_episode(twin, frames, state),
                     embed_clips_of_episode(self.encoder, frames, state), "a second fit with seed 0")

    def train_only(self) -> str:
        """The fit learns from the train split alone: a second fit (same seed) on a copy of the data set whose
        test episodes are other frames and states embeds as the first. (A fit may read test episodes for a
        held-out diagnostic, as mfTCN's does, but its weights must not depend on them.)"""
        assert self.encoder is not None and self.dataset is not None
        if not self.encoder.needs_fit:
            return "needs_fit is False: nothing trained"
        config = {**self.dataset.config, "name": "conformance-other-test"}
        other = ensure_dataset(self.home.datasets, config, _other_test_episodes, show_progress=False)
        twin = self._new()
        self._fit(twin, "fit-other-test", other)
        frames, state = self._episodes()[0]
        return _same(embed_clips_of_episode(twin, frames, state),
                     embed_clips_of_episode(self.encoder, frames, state), "test episodes replaced")

    def resume(self) -> str:
        """A fit killed half-way and started again in its folder (a fresh instance, as after a crash) ends
        where an uninterrupted fit does."""
        assert self.encoder is not None and self.prepared is not None
        if not self.encoder.needs_fit:
            return "needs_fit is False: nothing trained"
        total = fit_budget(self.name, self.prepared.config["encoder"].get("train", {})).steps

        def kill(step: int, *_: Any) -> None:
            if step >= max(1, total // 2):
                raise _Killed

        try:
            self._fit(self._new(), "fit-killed", progress=kill)
        except _Killed:
            pass
        steps: list[int] = []
        resumed = self._new()
        self._fit(resumed, "fit-killed", progress=lambda step, *_: steps.append(step))
        frames, state = self._episodes()[0]
        line = _same(embed_clips_of_episode(resumed, frames, state),
                     embed_clips_of_episode(self.encoder, frames, state), "killed at step "
                     f"{max(1, total // 2)} of {total} and restarted, vs uninterrupted")
        start = f"went on from step {steps[0]}" if steps and steps[0] > 1 else "started again from step 1"
        return f"{line}; the restarted fit {start}"

    def save_load(self) -> str:
        assert self.encoder is not None
        path = self.workdir / "saved" / "model.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        self.encoder.save(path)
        loaded = self._new()
        loaded.load(path)
        attach_feature_cache(loaded, self.dataset, self.home, show_progress=False)
        frames, state = self._episodes()[0]
        return _same(embed_clips_of_episode(loaded, frames, state),
                     embed_clips_of_episode(self.encoder, frames, state), "loaded vs saved")

    def device(self) -> str:
        """The saved encoder placed on the check's device embeds as on the CPU (a GPU sums in other orders)."""
        assert self.encoder is not None
        placed = self._new()
        if not isinstance(placed, DevicePlaced):
            return f"no to_device: runs on the CPU whatever --device asks ({self.placement.device} asked)"
        placed.to_device(self.placement.torch_device)
        placed.load(self.workdir / "saved" / "model.pt")
        attach_feature_cache(placed, self.dataset, self.home, show_progress=False, placement=self.placement)
        frames, state = self._episodes()[0]
        with full_float32():  # this compares placement, not TF32's rounding
            on_device = embed_clips_of_episode(placed, frames, state)
        return _same(on_device, embed_clips_of_episode(self.encoder, frames, state),
                     f"to_device({self.placement.device}) vs the CPU",
                     DEVICE_TOLERANCE if self.placement.is_cuda else TOLERANCE)

    def shapes(self) -> str:
        """The untrained encoder, built as each registered control task builds it (that task's encoder config,
        frame size and state size), embeds random clips to the right shape: a plugin that hard-codes the
        probe's 48x96 frames or 4-d state fails here, not hours into a cheetah run."""
        seen: dict[tuple[int, int, int], str] = {}
        for task in sorted(registry.entries("tasks")):
            try:
                prepared = prepare(RunRequest(self.name, task, None, 0, self.overrides, device="cpu"))
            except BenchError:
                continue  # a task that does not serve this encoder (imitation and a policy-trained encoder)
            data = prepared.task.dataset_config
            if not isinstance(data, Mapping) or data.get("domain") not in SUITE_DOMAINS:
                continue
            shape = (int(data["height"]), int(data["width"]), suite_state_size(data["domain"]))
            if shape in seen:
                continue
            seen[shape] = task
            encoder = construct_encoder(prepared.encoder_entry, prepared.config["encoder"], 0, shape[:2])
            if encoder.needs_fit:  # fitted first, with the check's budget, on synthetic frames of this size
                self._fit_at(encoder, shape[:2])
            info = encoder.info
            rng = np.random.default_rng(0)
            frames = rng.integers(0, 256, (2, info.frames, shape[0], shape[1], 3), dtype=np.uint8)
            state = visible(encoder, "state", rng.standard_normal((2, info.frames, shape[2])))
            try:
                check_embeddings(encoder, encoder.embed(ClipBatch(frames, state)), 2)
            except Exception as exc:  # noqa: BLE001 - whatever a plugin raises is this check's answer
                raise _Failed(f"{task} ({shape[1]}x{shape[0]} frames, {shape[2]}-d state): "
                              f"{type(exc).__name__}: {exc}") from None
        return ", ".join(f"{w}x{h} frames, {n}-d state ({task})" for (h, w, n), task in seen.items())

    def run(self) -> Iterator[CheckLine]:
        checks: list[tuple[str, Callable[[], str]]] = [
            ("spec", self.spec), ("construct", self.construct), ("privileged", self.privileged),
            ("metadata", self.metadata), ("fit", self.fit),
            ("embed", self.embed), ("embed_episode", self.embed_episode), ("streaming", self.streaming),
            ("determinism", self.determinism), ("train-only", self.train_only), ("resume", self.resume),
            ("save-load", self.save_load), ("device", self.device),
            ("shapes", self.shapes)]
        blocked = None
        for name, check in checks:
            if blocked is not None:
                yield CheckLine("skip", name, f"needs {blocked}")
                continue
            try:
                yield CheckLine("ok", name, check())
            except _Failed as exc:
                yield CheckLine("FAIL", name, str(exc))
            except Exception as exc:  # noqa: BLE001 - a plugin's failure of any kind is this check's result
                where = traceback.extract_tb(exc.__traceback__)[-1]
                yield CheckLine("FAIL", name, f"{type(exc).__name__}: {exc} ({Path(where.filename).name}:"
                                              f"{where.lineno})")
                if name in ("spec", "construct", "privileged", "fit"):
                    blocked = name


SUITE_DOMAINS = ("cartpole", "cheetah")  # the control suite's domains that registered tasks simulate


def suite_state_size(domain: str) -> int:
    """The size of the true state a suite domain records with each frame (`physics_state`)."""
    from mftcn_bench.rl.suite_env import physics_state
    from mftcn_bench.sim.rendering import ensure_gl

    ensure_gl()  # before dm_control is imported: it picks its GL back end then
    from dm_control import suite

    task = {"cartpole": "swingup", "cheetah": "run"}[domain]
    return int(physics_state(suite.load(domain, task).physics, domain).shape[0])


def check_encoder(name: str, overrides: Sequence[tuple[str, Any]] = (),
                  workdir: Path | None = None, device: str = "cpu") -> Iterator[CheckLine]:
    """The check lines of encoder `name`, computed in `workdir` (a temporary folder when None); the
    `device` check places it on `device`."""
    if workdir is not None:
        yield from EncoderCheck(name, workdir, overrides, device).run()
        return
    with tempfile.TemporaryDirectory(prefix="mftcn-check-") as tmp:
        yield from EncoderCheck(name, Path(tmp), overrides, device).run()
