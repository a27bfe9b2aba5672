"""`mftcn-bench bench`: the harness's speed, each figure a ratio against a reference measured in the same run.

Absolute times drift on a shared machine, so every figure is measured beside its reference, in the same
process, alternating blocks of the two (the order reversed every other round) so that a change of load
hits both. Everything runs with one torch thread (`torch.set_num_threads(1)`; the probe's child process also
with OMP/MKL/OpenBLAS at 1 thread), so a ratio is not an artefact of thread counts. The targets
(issue 7):

| figure | reference | target |
|---|---|---|
| rendering frames/s at a task's camera and size | dm_control's defaults (2048 shadow map, 4x MSAA) | >= 10x |
| streaming mfTCN step on the pretrained base, lookback 29 | streaming, lookback 1 | <= 1.3x the cost |
| PPO collection frames/s on mfTCN5 embeddings (96x48), each stream | the same loop rendering only | >= 0.7x |
| PPO collection frames/s on mfTCN5 embeddings (96x48), agent rate | the physics-rate stream; true state | report |
| PPO collection frames/s on true state | torchrl SerialEnv of 8 DMControlEnv | >= 2x |
| encoder training clips/s, mfTCN5 | each clip through the network on its own | report |
| feature-cache build frames/s (EfficientNet-Lite0 to block 10) | the raw base forward on the same frames | >= 0.8x |
| the frozen base's forward frames/s on the specs' engine (96x48, 160x160) | eager PyTorch | report |
| head training steps/s on the cache, mfTCN5 | end-to-end small-cnn mfTCN5 steps/s | report |
| clip embedding where clips share frames | each clip on its own; clips batched but not sharing | >= 1.5x |
| dataset read frames/s | the trainer's consumption of frames | >= 2x |
| peak RSS of the paper-scale probe | - | <= 4 GiB |

One function per figure returns `BenchRow`s; `run_bench` runs them and `format_table` prints them.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

GIB = 2**30


@dataclass(frozen=True)
class Target:
    """What a figure must reach: `ratio` (or `value`) `>=` or `<=` `bound`; `report` has no bound."""

    op: str  # ">=", "<=" or "report"
    bound: float = 0.0
    on: str = "ratio"  # "ratio" or "value"
    unit: str = "x"

    def met(self, value: float | None, ratio: float | None) -> bool | None:
        measured = ratio if self.on == "ratio" else value
        if self.op == "report" or measured is None or not math.isfinite(measured):
            return None
        return measured >= self.bound if self.op == ">=" else measured <= self.bound

    def __str__(self) -> str:
        return "report" if self.op == "report" else f"{self.op} {self.bound:g}{self.unit}"


@dataclass(frozen=True)
class BenchRow:
    """One measured figure beside its reference."""

    figure: str
    value: float
    unit: str
    reference: str  # what it is compared with
    reference_value: float | None
    ratio: float | None
    target: Target
    note: str = ""

    @property
    def met(self) -> bool | None:
        return self.target.met(self.value, self.ratio)

    def cells(self) -> dict[str, str]:
        ref = self.reference if self.reference_value is None else \
            f"{self.reference}: {_num(self.reference_value)} {self.unit}"
        met = {True: "yes", False: "NO", None: "report"}[self.met]
        return {"figure": self.figure, "value": f"{_num(self.value)} {self.unit}", "reference": ref,
                "ratio": "-" if self.ratio is None else f"{self.ratio:.2f}x", "target": str(self.target),
                "met": met}


def _num(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:.3g}"


@dataclass(frozen=True)
class Sizes:
    """How much work each figure measures: `QUICK` (CI, a minute or two) or `FULL` (docs/PERFORMANCE.md)."""

    name: str
    rounds: int  # alternations of subject and reference (after one untimed warm-up round)
    render_frames: int  # frames per block
    render_rounds: int
    stream_steps: int  # pushes per block (short blocks, many rounds: load on a shared machine changes fast)
    stream_rounds: int
    ppo_envs: int
    ppo_pixel_steps: int  # agent steps per collected batch (one episode, action repeat 8) from pixels
    ppo_state_steps: int  # the same on true state
    ppo_block_s: float  # each alternation block collects batches for at least this long
    data_train: int  # rendered cartpole episodes (96x48, 2 views) for training and reading
    data_length: int
    train_steps: int  # training steps per block
    embed_frames: int  # frames of the episode embedded per block
    probe_length: int  # frames per synthetic probe episode (160x160)
    probe_train: tuple[int, ...]  # train-episode counts embedded (plus one test episode each)
    probe_fit_fraction: float  # of the paper's 160,000 + 20,000 frames for the MLP fit's measurement
    probe_fit_epochs: int | None  # cap on the MLP's epochs there (None: the paper preset's)


QUICK = Sizes("quick", rounds=2, render_frames=4, render_rounds=4, stream_steps=5, stream_rounds=6,
              ppo_envs=8, ppo_pixel_steps=4, ppo_state_steps=25, ppo_block_s=1.0, data_train=3, data_length=100,
              train_steps=2, embed_frames=60, probe_length=100, probe_train=(1,), probe_fit_fraction=0.1,
              probe_fit_epochs=2)
FULL = Sizes("full", rounds=4, render_frames=10, render_rounds=20, stream_steps=10, stream_rounds=24,
             ppo_envs=8, ppo_pixel_steps=25, ppo_state_steps=125, ppo_block_s=5.0, data_train=4, data_length=400,
             train_steps=6, embed_frames=400, probe_length=1000, probe_train=(1, 4), probe_fit_fraction=1.0,
             probe_fit_epochs=None)


# -- measuring -------------------------------------------------------------------------------------------
Block = Callable[[], tuple[float, float]]  # runs once; returns (work done, seconds it took)


def timed(fn: Callable[[], Any], work: float) -> Block:
    """A block that times `fn()` and counts `work` units for it."""

    def block() -> tuple[float, float]:
        began = time.perf_counter()
        fn()
        return work, time.perf_counter() - began

    return block


def alternate(blocks: Mapping[str, Block], rounds: int, warmup: bool = True) -> dict[str, float]:
    """Work per second of each block, run `rounds` times in alternation (order reversed every other
    round) after one untimed warm-up round."""
    names = list(blocks)
    if warmup:
        for name in names:
            blocks[name]()
    work, seconds = dict.fromkeys(names, 0.0), dict.fromkeys(names, 0.0)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            done, took = blocks[name]()
            work[name] += done
            seconds[name] += took
    return {name: work[name] / seconds[name] for name in names}


def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)


# -- rendering ---------------------------------------------------------------------------------------------
def bench_render(sizes: Sizes, task: str = "swingup") -> BenchRow:
    """Frames/s of the harness's renderer (the task's camera, size and render settings) against
    dm_control's `physics.render` at the same camera and size with the suite's default quality."""
    from mftcn_bench.sim.rendering import MultiViewRenderer, ensure_gl

    ensure_gl()  # before dm_control is imported: it picks its GL backend then
    from dm_control import suite

    env_config = _control_task(task, "true-state").env_config
    h, w, camera = env_config.height, env_config.width, env_config.camera
    ours = suite.load(env_config.domain, env_config.task, task_kwargs={"random": 0})
    default = suite.load(env_config.domain, env_config.task, task_kwargs={"random": 0})
    renderer = MultiViewRenderer(ours.physics, [camera], h, w, env_config.render)
    quality = default.physics.model.vis.quality
    n = sizes.render_frames

    def render_ours() -> None:
        for _ in range(n):
            renderer.render()

    def render_default() -> None:
        for _ in range(n):
            default.physics.render(h, w, camera_id=camera)

    rates = alternate({"ours": timed(render_ours, n), "default": timed(render_default, n)}, sizes.render_rounds)
    return BenchRow(f"rendering {w}x{h} '{camera}' ({task}), frames/s", rates["ours"], "frames/s",
                    f"dm_control defaults (shadow {quality.shadowsize}, {quality.offsamples}x MSAA)",
                    rates["default"], rates["ours"] / rates["default"], Target(">=", 10),
                    f"ours: {env_config.render}, buffer {w}x{h}")


# -- streaming ------------------------------------------------------------------------------------------
STREAM_ENVS, STREAM_SHAPE = 8, (48, 96)


def _streamer(frames: int, stride: int):
    """A warmed-up streaming mfTCN (mftcn4's network, clip shape frames x stride) over 8 environments and
    the frame it is pushed each step."""

    from mftcn_bench.core.registry import get
    from mftcn_bench.core.specs import EncoderSpec
    from mftcn_bench.encoders.mftcn import MfTCNEncoder

    base = get("encoders", "mftcn4").spec
    spec = EncoderSpec(f"stream{frames}x{stride}", "mftcn", "benchmark", frames, stride, base.embedding_dim,
                       base.model, base.train)
    encoder = MfTCNEncoder(spec, image_shape=STREAM_SHAPE, seed=0)
    stream = encoder.streaming(STREAM_ENVS)
    frame = np.random.default_rng(frames).integers(0, 255, (STREAM_ENVS, *STREAM_SHAPE, 3), dtype=np.uint8)
    stream.push(frame, np.ones(STREAM_ENVS, bool))
    return stream, frame


def bench_streaming(sizes: Sizes) -> BenchRow:
    """Cost of one streaming step of 8 environments at 96x48: lookback 29 (5 frames at stride 7) against
    lookback 1."""

    _one_thread()
    long_stream, long_frame = _streamer(5, 7)
    short_stream, short_frame = _streamer(1, 1)
    running = np.zeros(STREAM_ENVS, bool)
    n = sizes.stream_steps

    def push(stream, frame) -> Callable[[], None]:
        def run() -> None:
            for _ in range(n):
                stream.push(frame, running)
        return run

    rates = alternate({"29": timed(push(long_stream, long_frame), n),
                       "1": timed(push(short_stream, short_frame), n)}, sizes.stream_rounds)
    long_ms, short_ms = 1e3 / rates["29"], 1e3 / rates["1"]
    return BenchRow("streaming mfTCN step, lookback 29 (8 envs, 96x48)", long_ms, "ms", "lookback 1", short_ms,
                    long_ms / short_ms, Target("<=", 1.3, unit="x the cost"),
                    "EfficientNet-Lite0 base to block 10: one base pass per new frame whatever the lookback")


# -- PPO collection ----------------------------------------------------------------------------------------
def _control_task(task: str, encoder: str, overrides: Sequence[tuple[str, Any]] = ()):
    from mftcn_bench.run.runner import RunRequest, prepare

    return prepare(RunRequest(encoder, task, "paper", 0, tuple(overrides))).task


class _RenderOnlyObserver:
    """Takes the rendered frames and embeds nothing (zeros of the encoder's size): the reference loop that
    renders what the encoder would see, to tell the encoder's cost from the renderer's."""

    def __init__(self, embedding_dim: int, num_envs: int) -> None:
        self._zeros = np.zeros((num_envs, embedding_dim), dtype=np.float32)

    def push(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> np.ndarray:
        return self._zeros

    def observe(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> None:
        """Nothing to keep."""


def _suite_collector(encoder_name: str, sizes: Sizes, agent_steps: int, task: str = "swingup", device=None,
                     render_only: bool = False):
    """torchrl's Collector over the harness's SuiteBatchEnv with the PPO policy of the task (untrained),
    as `train_ppo` builds them; one batch is one episode of `agent_steps` agent steps. With `device`, the
    encoder (when it can move) and the policy compute there, as in a run with --device. With
    `render_only`, the environment renders the frames the encoder would see but the encoder never runs."""
    from mftcn_bench.core.device import DevicePlaced
    from mftcn_bench.core.specs import encoder_spec_from_config
    from mftcn_bench.encoders.base import uses_pixels
    from mftcn_bench.rl.observation import observed_env
    from mftcn_bench.rl.observers import make_observer
    from mftcn_bench.rl.ppo import PolicyNetworks
    from mftcn_bench.run.runner import RunRequest, prepare

    repeat = _control_task(task, "true-state").env_config.action_repeat
    prepared = prepare(RunRequest(encoder_name, task, "paper", 0,
                                  (("task.env.episode_length", agent_steps * repeat),)))
    control, data = prepared.task, prepared.task.dataset_config
    spec = encoder_spec_from_config(prepared.encoder_entry.description, prepared.config["encoder"])
    encoder = prepared.encoder_entry.load()(spec, image_shape=(data["height"], data["width"]), seed=0)
    if device is not None and isinstance(encoder, DevicePlaced):
        encoder.to_device(device)
    info = encoder.info
    observer = (_RenderOnlyObserver(info.embedding_dim, sizes.ppo_envs) if render_only
                else make_observer(encoder, sizes.ppo_envs))
    env = observed_env(control.env_config, sizes.ppo_envs, 0, observer, info.embedding_dim, uses_pixels(encoder),
                       lookback=info.lookback)
    nets = PolicyNetworks(env, control.ppo, None).to(device or "cpu")
    return _collector(env, nets.policy, sizes.ppo_envs * agent_steps, device), repeat


def _collector(env, policy, batch: int, device=None):
    from torchrl.collectors import Collector

    placed = {} if device is None else {"env_device": "cpu", "policy_device": device, "storing_device": device}
    return Collector(env, policy, frames_per_batch=batch, total_frames=-1,
                     reset_at_each_iter=True, auto_register_policy_transforms=False, **placed)


def _serial_collector(sizes: Sizes, frame_skip: int, task: str = "swingup"):
    """The reference: torchrl's SerialEnv of DMControlEnv (state observations) with `frame_skip`, the same
    number of environments and policy network, and batches of as many simulator frames."""
    from mftcn_bench.sim.rendering import ensure_gl

    ensure_gl()
    from torchrl.envs import CatTensors, Compose, DoubleToFloat, SerialEnv, TransformedEnv
    from torchrl.envs.libs.dm_control import DMControlEnv

    from mftcn_bench.rl.ppo import PolicyNetworks

    control = _control_task(task, "true-state")
    config = control.env_config

    def make() -> DMControlEnv:
        return DMControlEnv(config.domain, config.task, frame_skip=frame_skip)

    probe = make()
    keys = list(probe.observation_spec.keys())
    probe.close()
    env = TransformedEnv(SerialEnv(sizes.ppo_envs, make), Compose(CatTensors(keys, "observation"), DoubleToFloat()))
    batch = sizes.ppo_envs * sizes.ppo_state_steps * config.action_repeat // frame_skip
    return _collector(env, PolicyNetworks(env, control.ppo, None).policy, batch), frame_skip


def _collect_block(collector, repeat: int, min_seconds: float) -> Block:
    """Collected batches until `min_seconds` have passed (so a fast and a slow collector alternate in
    blocks of similar length); work = simulator frames (agent steps x action repeat)."""
    batches = iter(collector)

    def block() -> tuple[float, float]:
        began, frames = time.perf_counter(), 0.0
        while not frames or time.perf_counter() - began < min_seconds:
            frames += next(batches).numel() * repeat
        return frames, time.perf_counter() - began

    return block


def _collect(collectors: Mapping[str, tuple[Any, int]], sizes: Sizes) -> dict[str, float]:
    try:
        return alternate({name: _collect_block(*pair, sizes.ppo_block_s) for name, pair in collectors.items()},
                         sizes.rounds)
    finally:
        for collector, _ in collectors.values():
            collector.shutdown()


STREAMS = {"agent-rate": "swingup", "physics-rate": "swingup-physics-rate"}  # stream -> the swing-up task on it


def bench_ppo_pixels(sizes: Sizes) -> list[BenchRow]:
    """PPO collection frames/s on mfTCN5 embeddings of 96x48 frames (the encoder's spec, so its frozen base)
    on each stream of the encoder's frames: against the same loop rendering the same frames without the
    encoder (the target: the encoder's share of a rollout), the agent-rate stream against the physics-rate
    one, and against true state (no rendering). All: the harness's SuiteBatchEnv and torchrl's Collector."""
    _one_thread()
    steps = sizes.ppo_pixel_steps
    collectors = {"state": _suite_collector("true-state", sizes, steps)}
    for stream, task in STREAMS.items():
        collectors[stream] = _suite_collector("mftcn5", sizes, steps, task)
        collectors[f"{stream} render"] = _suite_collector("mftcn5", sizes, steps, task, render_only=True)
    rates = _collect(collectors, sizes)
    notes = {"agent-rate": "1 rendered frame and 1 base pass per agent step (action repeat 8), the head once",
             "physics-rate": "5 rendered frames and 5 base passes per agent step (action repeat 8), the head once"}
    rows = []
    for stream in STREAMS:
        figure = f"PPO collection on mfTCN5 embeddings, {stream} stream (96x48, {sizes.ppo_envs} envs)"
        rows.append(BenchRow(figure, rates[stream], "frames/s", "the same loop, rendering only",
                             rates[f"{stream} render"], rates[stream] / rates[f"{stream} render"], Target(">=", 0.7),
                             notes[stream]))
    figure = f"PPO collection on mfTCN5 embeddings, agent-rate stream (96x48, {sizes.ppo_envs} envs)"
    rows.append(BenchRow(figure, rates["agent-rate"], "frames/s", "the physics-rate stream", rates["physics-rate"],
                         rates["agent-rate"] / rates["physics-rate"], Target("report"), notes["agent-rate"]))
    rows.append(BenchRow(figure, rates["agent-rate"], "frames/s", "true state (no rendering)", rates["state"],
                         rates["agent-rate"] / rates["state"], Target("report"), notes["agent-rate"]))
    return rows


def bench_ppo_state(sizes: Sizes) -> list[BenchRow]:
    """PPO collection frames/s on true state: SuiteBatchEnv + Collector (action repeat 8) against a
    SerialEnv of DMControlEnv + Collector with torchrl's default frame_skip 1, and with frame_skip 8 (the
    same action repeat), all with `ppo_envs` environments."""
    _one_thread()
    rates = _collect({"ours": _suite_collector("true-state", sizes, sizes.ppo_state_steps),
                      "skip1": _serial_collector(sizes, 1), "skip8": _serial_collector(sizes, 8)}, sizes)
    figure = f"PPO collection on true state ({sizes.ppo_envs} envs, action repeat 8)"
    serial = f"torchrl SerialEnv of {sizes.ppo_envs} DMControlEnv"
    return [BenchRow(figure, rates["ours"], "frames/s", f"{serial} (frame_skip 1, its default)", rates["skip1"],
                     rates["ours"] / rates["skip1"], Target(">=", 2)),
            BenchRow(figure, rates["ours"], "frames/s", f"{serial} (frame_skip 8, as ours)", rates["skip8"],
                     rates["ours"] / rates["skip8"], Target(">=", 2))]


# -- encoder training, clip embedding and dataset reading -------------------------------------------------
def cartpole_dataset(workdir: Path, sizes: Sizes):
    """A rendered multi-view cartpole dataset (the probe's 96x48 data at `sizes`), collected once into
    `workdir` and reused by the figures that read it."""
    from mftcn_bench.data.cartpole import collect_episode
    from mftcn_bench.data.dataset import ensure_dataset

    config = dict(_control_task("cartpole-probe", "mftcn5").dataset_config)
    config.update(train_episodes=sizes.data_train, test_episodes=1, episode_length=sizes.data_length)
    return ensure_dataset(workdir / "datasets", config, collect_episode, show_progress=False)


def _mftcn5(dataset, seed: int = 0):
    from mftcn_bench.core.registry import get
    from mftcn_bench.encoders.mftcn import MfTCNEncoder

    return MfTCNEncoder(get("encoders", "mftcn5").spec, image_shape=dataset.image_shape, seed=seed)


def _train_config(encoder, dataset):
    from dataclasses import replace

    return replace(encoder.train_config, checkpoint_every=0, episode_pool=min(encoder.train_config.episode_pool,
                                                                           len(dataset.episodes("train"))))


def _steps_block(train: Callable[[Any], None], steps: int, clips_per_step: int) -> Block:
    """Runs `train(progress)` for `steps` steps; times the steps after the first (from the trainer's own
    progress calls, so pool loading at its start is not counted); work = clips."""

    def block() -> tuple[float, float]:
        stamps: list[float] = []
        train(lambda done, total, stats: stamps.append(time.perf_counter()))
        return float(clips_per_step * (len(stamps) - 1)), stamps[-1] - stamps[0]

    return block


def _trainer(encoder, dataset, workdir: Path, steps: int, naive: bool) -> Callable[[Any], None]:
    """The harness's `train_multiview`, or the naive trainer: the same batches, loss and Adam, but every clip
    through the network on its own (base CNN on each of its frames, then the head)."""
    import torch

    from mftcn_bench.encoders.base import FitBudget
    from mftcn_bench.encoders.losses import multiview_npairs_loss
    from mftcn_bench.encoders.sampling import plan_batch
    from mftcn_bench.encoders.training import gather_clips, run_training, train_multiview

    config = _train_config(encoder, dataset)
    spec, net = encoder.spec, encoder.net
    min_gap = max(config.alpha, spec.lookback)

    def naive_loss(pool, rng: np.random.Generator):
        lengths = {i: ep.length for i, ep in pool.episodes.items()}
        plan = plan_batch(rng, sorted(pool.episodes), lengths, config.batch_timesteps,
                          config.episodes_per_batch, min_gap)
        clips = gather_clips(pool, plan.episodes, plan.times, spec.frames, spec.stride)
        views, count = clips.shape[:2]
        batch = torch.from_numpy(clips.reshape(views * count, *clips.shape[2:])).permute(0, 1, 4, 2, 3)
        embeddings = torch.cat([net(clip[None]) for clip in batch]).reshape(views, count, -1)
        return multiview_npairs_loss(embeddings, config.reg_lambda), {}

    def train(progress) -> None:
        budget = FitBudget(steps=steps)
        workdir.mkdir(parents=True, exist_ok=True)
        if naive:
            run_training(net, dataset, config, budget, progress, workdir, seed=0, batch_loss=naive_loss)
        else:
            train_multiview(net, dataset, config, budget, progress, workdir, frames=spec.frames,
                            stride=spec.stride, seed=0)

    return train


def bench_training(sizes: Sizes, workdir: Path) -> BenchRow:
    """Clips/s of mfTCN5's trainer (`train_multiview`: n-pairs batches of 32 time steps x 2 views) against
    a naive trainer that runs each clip through the network separately."""
    _one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    ours, naive = _mftcn5(dataset), _mftcn5(dataset)
    clips = _train_config(ours, dataset).batch_timesteps * len(dataset.cameras)
    steps = sizes.train_steps + 1
    rates = alternate({"ours": _steps_block(_trainer(ours, dataset, workdir / "ours", steps, False), steps, clips),
                       "naive": _steps_block(_trainer(naive, dataset, workdir / "naive", steps, True), steps, clips)},
                      sizes.rounds, warmup=False)
    return BenchRow("encoder training, mfTCN5 (96x48, 64 clips a step)", rates["ours"], "clips/s",
                    "naive: each clip separately", rates["naive"], rates["ours"] / rates["naive"],
                    Target("report"), "n-pairs clips never share frames (time steps >= lookback apart)")


def bench_feature_cache(sizes: Sizes, workdir: Path) -> BenchRow:
    """Frames/s of building the per-frame feature cache (decode, base forward, write, checksum) against the
    base's forward pass alone on the same frames."""
    import shutil

    from mftcn_bench.encoders.feature_cache import base_features, ensure_feature_cache

    _one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    base = _mftcn5(dataset).frozen_base()
    episodes = dataset.episodes("train") + dataset.episodes("test")
    frames = sum(dataset.episode_length(i) for i in episodes) * len(dataset.cameras)
    views = [dataset.load(i).frames for i in episodes]

    def build() -> None:
        shutil.rmtree(workdir / "features", ignore_errors=True)
        ensure_feature_cache(workdir / "features", dataset, base, base.identity(), show_progress=False)

    def forward() -> None:
        for episode in views:
            np.stack([base_features(base, view, 64) for view in episode])

    rates = alternate({"cache": timed(build, frames), "forward": timed(forward, frames)}, sizes.rounds)
    return BenchRow("feature-cache build, EfficientNet-Lite0 to block 10 (96x48, 2 views)", rates["cache"],
                    "frames/s", "the base's forward alone", rates["forward"], rates["cache"] / rates["forward"],
                    Target(">=", 0.8), "decode, forward, write and checksum every frame of every view")


ENGINE_BATCH = 32  # frames a rollout step embeds at once: one per environment of swingup's [ppo] num_envs


def bench_base_engine(sizes: Sizes) -> list[BenchRow]:
    """Frames/s of the frozen base (mfTCN5's `[model.base]`, its engine) against the same base in eager
    PyTorch, at the two swing-up image sizes, a rollout step's batch of frames."""
    from dataclasses import replace

    import torch

    from mftcn_bench.core.registry import get
    from mftcn_bench.encoders.bases import BaseConfig, build_base

    _one_thread()
    config = BaseConfig(**get("encoders", "mftcn5").spec.model["base"])
    bases = {"engine": build_base(config), "eager": build_base(replace(config, engine="torch"))}
    rows = []
    for height, width in ((48, 96), (160, 160)):
        images = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (ENGINE_BATCH, 3, height, width),
                                                                    dtype=np.uint8))
        repeat = max(1, sizes.embed_frames // ENGINE_BATCH)

        def forward(base, images=images, repeat=repeat) -> Callable[[], None]:
            return lambda: [base(images) for _ in range(repeat)]

        rates = alternate({name: timed(forward(base), repeat * ENGINE_BATCH) for name, base in bases.items()},
                          sizes.rounds)
        rows.append(BenchRow(f"frozen base forward, {config.engine} ({width}x{height}, batch {ENGINE_BATCH})",
                             rates["engine"], "frames/s", "eager PyTorch", rates["eager"],
                             rates["engine"] / rates["eager"], Target("report"),
                             f"EfficientNet-Lite0 to block {config.layer}, one thread"))
    return rows


def bench_head_training(sizes: Sizes, workdir: Path) -> BenchRow:
    """Steps/s of mfTCN5's head trained on the feature cache against today's end-to-end small-cnn mfTCN5."""
    from dataclasses import replace

    from mftcn_bench.core.registry import get
    from mftcn_bench.encoders.feature_cache import ensure_feature_cache
    from mftcn_bench.encoders.mftcn import MfTCNEncoder

    _one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    head = _mftcn5(dataset)
    base = head.frozen_base()
    head.use_feature_cache(ensure_feature_cache(workdir / "features-head", dataset, base, base.identity(),
                                                show_progress=False))
    spec = get("encoders", "mftcn5").spec
    small = replace(spec, model={**spec.model, "base": {"name": "small-cnn"}})
    scratch = MfTCNEncoder(small, image_shape=dataset.image_shape, seed=0)
    steps = sizes.train_steps + 1

    def trainer(encoder, folder: str) -> Callable[[Any], None]:
        from mftcn_bench.encoders.base import FitBudget
        from mftcn_bench.encoders.training import train_multiview

        config = _train_config(encoder, dataset)

        def train(progress) -> None:
            (workdir / folder).mkdir(parents=True, exist_ok=True)
            train_multiview(encoder.net, dataset, config, FitBudget(steps), progress, workdir / folder,
                            frames=encoder.spec.frames, stride=encoder.spec.stride, seed=0,
                            features=encoder.training_features())
        return train

    rates = alternate({"head": _steps_block(trainer(head, "head"), steps, 1),
                       "scratch": _steps_block(trainer(scratch, "scratch"), steps, 1)}, sizes.rounds, warmup=False)
    return BenchRow("head training on the feature cache, mfTCN5 (96x48, 64 clips a step)", rates["head"],
                    "steps/s", "end-to-end small-cnn mfTCN5", rates["scratch"], rates["head"] / rates["scratch"],
                    Target("report"), "the head reads cached base features; small-cnn decodes frames and "
                    "trains its CNN")


def bench_embedding(sizes: Sizes, workdir: Path) -> list[BenchRow]:
    """Clips/s embedding every clip of an episode (consecutive clips share n-1 frames) with the encoder's
    `embed_episode` (one base-CNN pass per frame) against each clip on its own, and against the clips
    batched (256) without sharing frames."""

    from mftcn_bench.data.clips import clip_indices
    from mftcn_bench.encoders.base import ClipBatch

    _one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    encoder = _mftcn5(dataset)
    frames = dataset.load(dataset.episodes("train")[0]).frames[0, :sizes.embed_frames]
    n = len(frames)
    index = clip_indices(np.arange(n), encoder.spec.frames, encoder.spec.stride)

    def one_by_one() -> None:
        for rows in index:
            encoder.embed(ClipBatch(frames[rows][None]))

    def batched() -> None:
        for start in range(0, n, 256):
            encoder.embed(ClipBatch(frames[index[start:start + 256]]))

    rates = alternate({"ours": timed(lambda: encoder.embed_episode(frames), n), "separately": timed(one_by_one, n),
                       "batched": timed(batched, n)}, sizes.rounds)
    figure = "clip embedding, mfTCN5, clips sharing frames (96x48)"
    return [BenchRow(figure, rates["ours"], "clips/s", "naive: each clip separately", rates["separately"],
                     rates["ours"] / rates["separately"], Target(">=", 1.5)),
            BenchRow(figure, rates["ours"], "clips/s", "clips batched, frames not shared", rates["batched"],
                     rates["ours"] / rates["batched"], Target(">=", 1.5))]


def bench_dataset_read(sizes: Sizes, workdir: Path) -> BenchRow:
    """Frames/s decoded from dataset chunks (every view, checksum checked, no cache) against the frames/s
    the mfTCN5 trainer's batches consume (clips/s x frames per clip), measured alternately."""
    from mftcn_bench.data.dataset import MultiViewDataset

    _one_thread()
    dataset = cartpole_dataset(workdir, sizes)
    uncached = MultiViewDataset(dataset.root, cache_episodes=0)
    episodes = uncached.episodes("train") + uncached.episodes("test")
    frames = sum(uncached.episode_length(i) for i in episodes) * len(uncached.cameras)
    encoder = _mftcn5(dataset)
    clips = _train_config(encoder, dataset).batch_timesteps * len(dataset.cameras)
    steps = sizes.train_steps + 1

    def read_all() -> None:
        for i in episodes:
            uncached.load(i)

    rates = alternate({"read": timed(read_all, frames),
                       "train": _steps_block(_trainer(encoder, dataset, workdir / "read", steps, False), steps,
                                             clips * encoder.spec.frames)}, sizes.rounds, warmup=False)
    return BenchRow("dataset read (96x48 chunks, 2 views)", rates["read"], "frames/s",
                    "mfTCN5 trainer's consumption", rates["train"], rates["read"] / rates["train"], Target(">=", 2),
                    "the trainer reloads one pool episode every 10 steps; consumption counts every clip frame")


# -- probe memory --------------------------------------------------------------------------------------------
def bench_probe_rss(sizes: Sizes, workdir: Path) -> BenchRow:
    """Peak RSS of `cartpole-probe` (paper preset at 160x160, mftcn4) at 180,000 frames: the MLP fit measured
    at that size on features of the real shapes, the embedding phase measured on a few synthetic episodes
    plus the bytes of the features it would keep (`bench_probe`)."""
    from mftcn_bench.perf import bench_probe

    size, full = 160, bench_probe.PAPER_TRAIN_FRAMES + bench_probe.PAPER_TEST_FRAMES
    root = bench_probe.write_dataset(workdir / "probe-datasets", max(sizes.probe_train), 1, sizes.probe_length,
                                     size)
    embedding = [bench_probe.in_child("embed", str(bench_probe.subset(root, k, 1, workdir / f"probe-{k}")))
                 for k in sizes.probe_train]
    train, test = (f * sizes.probe_fit_fraction for f in (bench_probe.PAPER_TRAIN_FRAMES,
                                                          bench_probe.PAPER_TEST_FRAMES))
    epochs = [] if sizes.probe_fit_epochs is None else [str(sizes.probe_fit_epochs)]
    fit = bench_probe.in_child("fit", str(int(train)), str(int(test)), "1000", *epochs)
    peak = bench_probe.paper_scale_peak(embedding, fit, full)
    measured = ", ".join(f"{m.frames:,} frames embedded: {m.embed_peak / GIB:.2f} GiB" for m in embedding)
    fitted = f"MLP fit on {fit.frames:,} frames: {fit.fit_peak / GIB:.2f} GiB"
    scale = "" if sizes.probe_length == 1000 and sizes.probe_fit_fraction == 1 else " (quick: not the paper's size)"
    return BenchRow(f"probe peak RSS, 180k frames x 2 views at {size}x{size}{scale}", peak / GIB, "GiB", "-", None,
                    None, Target("<=", 4, on="value", unit=" GiB"),
                    f"{measured}; {fitted}; embedding grows {bench_probe.embedding_growth(embedding) / 1024:.2f} KiB "
                    f"per frame")


# -- the whole suite --------------------------------------------------------------------------------------
FIGURES = ("render", "streaming", "ppo-pixels", "ppo-state", "training", "feature-cache", "base-engine",
           "head-training", "embedding", "dataset", "probe-rss", "device")
# Run by default only on a GPU (`--device` resolving to CUDA); on the CPU `--only device` checks the path.
ON_DEVICE_ONLY = ("device",)


def run_bench(sizes: Sizes, only: Sequence[str] = FIGURES, workdir: Path | None = None,
              progress: Callable[[str], None] | None = None, placement=None) -> list[BenchRow]:
    """The figures named in `only`, in FIGURES order; data goes to `workdir` (a temporary folder if None);
    "device" compares `placement`'s device (default: the CPU) with the CPU."""
    from mftcn_bench.core.device import CPU
    from mftcn_bench.perf.bench_device import bench_device

    unknown = sorted(set(only) - set(FIGURES))
    if unknown:
        from mftcn_bench.core.errors import SpecError

        raise SpecError(f"unknown benchmark(s) {unknown}; choose from {', '.join(FIGURES)}")
    with tempfile.TemporaryDirectory(prefix="mftcn-bench-") as tmp:
        work = Path(workdir) if workdir is not None else Path(tmp)
        steps: dict[str, Callable[[], BenchRow | list[BenchRow]]] = {
            "render": lambda: [bench_render(sizes, "swingup"), bench_render(sizes, "swingup-moving")],
            "streaming": lambda: bench_streaming(sizes),
            "ppo-pixels": lambda: bench_ppo_pixels(sizes),
            "ppo-state": lambda: bench_ppo_state(sizes),
            "training": lambda: bench_training(sizes, work),
            "feature-cache": lambda: bench_feature_cache(sizes, work),
            "base-engine": lambda: bench_base_engine(sizes),
            "head-training": lambda: bench_head_training(sizes, work),
            "embedding": lambda: bench_embedding(sizes, work),
            "dataset": lambda: bench_dataset_read(sizes, work),
            "probe-rss": lambda: bench_probe_rss(sizes, work),
            "device": lambda: bench_device(sizes, work, placement or CPU),
        }
        rows: list[BenchRow] = []
        for name in FIGURES:
            if name in only:
                began = time.monotonic()
                out = steps[name]()
                rows.extend(out if isinstance(out, list) else [out])
                if progress is not None:
                    progress(f"{name}: {time.monotonic() - began:.0f} s")
        return rows


def format_table(rows: Sequence[BenchRow]) -> str:
    """A markdown (github) table: figure, value, reference, ratio, target, met."""
    from tabulate import tabulate

    cells = [row.cells() for row in rows]
    return tabulate([list(c.values()) for c in cells], headers=list(cells[0]) if cells else [],
                    tablefmt="github", disable_numparse=True)


def machine_description() -> str:
    """One paragraph: date, CPU, cores, memory, load and library versions (for the report's header)."""
    import mujoco
    import torch
    import torchrl

    from mftcn_bench.core.provenance import versions

    mem_kib = next(int(line.split()[1]) for line in Path("/proc/meminfo").read_text().splitlines()
                   if line.startswith("MemTotal"))
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lib = versions()
    return (f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC; {lib['cpu']}, {os.cpu_count()} cores, {mem_kib / 2**20:.0f} GiB; "
            f"load average {load}; python {platform.python_version()}, torch {torch.__version__} "
            f"({torch.get_num_threads()} thread), torchrl {torchrl.__version__}, mujoco {mujoco.__version__}, "
            f"dm_control {lib.get('dm-control', lib.get('dm_control', '?'))}; MUJOCO_GL={os.environ.get('MUJOCO_GL')}")


def add_command(commands: argparse._SubParsersAction) -> None:
    """Add `bench` to the main command line."""
    bench = commands.add_parser("bench", help="speed benchmarks, each a ratio against a reference run beside it")
    bench.add_argument("--quick", action="store_true", help="CI sizes: about a minute or two on 2 cores")
    bench.add_argument("--out", help="also write the table, with the machine it ran on, to this markdown file")
    bench.add_argument("--only", help=f"comma-separated figures (default all; 'device' only on a GPU): "
                                      f"{', '.join(FIGURES)}")
    bench.add_argument("--device", help="the device of the 'device' figures, against the CPU (default "
                                        "$MFTCN_BENCH_DEVICE or auto)")
    bench.set_defaults(handler=cmd_bench)


def cmd_bench(args: argparse.Namespace) -> None:
    import sys

    from mftcn_bench.core.device import requested_device, resolve_device
    from mftcn_bench.sim.rendering import ensure_gl, follow_device, gl_renderer

    placement = resolve_device(requested_device(args.device))
    follow_device(placement.device)
    ensure_gl()
    _one_thread()
    sizes = QUICK if args.quick else FULL
    only = ([name.strip() for name in args.only.split(",")] if args.only else
            [f for f in FIGURES if f not in ON_DEVICE_ONLY or placement.is_cuda])
    began = time.monotonic()
    rows = run_bench(sizes, only, progress=lambda line: print(f"bench {line}", file=sys.stderr, flush=True),
                     placement=placement)
    table = format_table(rows)
    print(table)
    notes = list(dict.fromkeys(f"- {row.figure}: {row.note}" for row in rows if row.note))  # once per figure
    print("\n".join(notes))
    met = sum(row.met is True for row in rows)
    missed = [row.figure for row in rows if row.met is False]
    summary = f"{met} of {sum(row.met is not None for row in rows)} targets met ({sizes.name} sizes, " \
              f"{time.monotonic() - began:.0f} s)" + (f"; not met: {'; '.join(missed)}" if missed else "")
    summary += f"\ndevice: {placement.device}" + (f" ({placement.gpu})" if placement.gpu else "") + \
               f"; GL renderer: {gl_renderer()}"
    print(summary)
    if args.out:
        text = (f"# mftcn-bench bench ({sizes.name})\n\n{machine_description()}\n\n{table}\n\n"
                + "\n".join(notes) + f"\n\n{summary}\n")
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")
