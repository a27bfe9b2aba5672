"""The PPO collection figures: torchrl's Collector over the harness's SuiteBatchEnv, on mfTCN5 embeddings
(each stream of the encoder's frames) and on true state, against rendering only, true state and torchrl's
own SerialEnv of DMControlEnv.

`suite_collector` and `collect` also serve the device figures (`bench_device`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from mftcn_bench.perf.fixtures import control_task
from mftcn_bench.perf.timing import BenchRow, Block, Sizes, Target, alternate, one_thread


class _RenderOnlyObserver:
    """Takes the rendered frames and embeds nothing (zeros of the encoder's size): the reference loop that
    renders what the encoder would see, to tell the encoder's cost from the renderer's."""

    def __init__(self, embedding_dim: int, num_envs: int) -> None:
        self._zeros = np.zeros((num_envs, embedding_dim), dtype=np.float32)

    def push(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> np.ndarray:
        return self._zeros

    def observe(self, frames: np.ndarray | None, episode_start: np.ndarray, state: np.ndarray) -> None:
        """Nothing to keep."""


def suite_collector(encoder_name: str, sizes: Sizes, agent_steps: int, task: str = "swingup", device=None,
                    render_only: bool = False, overrides: tuple[tuple[str, Any], ...] = ()):
    """torchrl's Collector over the harness's SuiteBatchEnv with the PPO policy of the task (untrained),
    as `train_ppo` builds them; one batch is one episode of `agent_steps` agent steps. With `device`, the
    encoder (when it can move) and the policy compute there, as in a run with --device. With
    `render_only`, the environment renders the frames the encoder would see but the encoder never runs.
    `overrides` are spec overrides of the run (`--set`)."""
    from mftcn_bench.core.device import DevicePlaced
    from mftcn_bench.core.specs import encoder_spec_from_config
    from mftcn_bench.encoders.base import uses_pixels
    from mftcn_bench.rl.observation import observed_env
    from mftcn_bench.rl.observers import make_observer
    from mftcn_bench.rl.ppo import PolicyNetworks
    from mftcn_bench.run.plan import RunRequest, prepare

    repeat = control_task(task, "true-state").env_config.action_repeat
    prepared = prepare(RunRequest(encoder_name, task, "paper", 0,
                                  (("task.env.episode_length", agent_steps * repeat), *overrides)))
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

    control = control_task(task, "true-state")
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


def collect(collectors: Mapping[str, tuple[Any, int]], sizes: Sizes) -> dict[str, float]:
    """Simulator frames/s of each (collector, action repeat), alternated; every collector is shut down
    afterwards, also when a block fails."""
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
    one_thread()
    steps = sizes.ppo_pixel_steps
    collectors = {"state": suite_collector("true-state", sizes, steps)}
    for stream, task in STREAMS.items():
        collectors[stream] = suite_collector("mftcn5", sizes, steps, task)
        collectors[f"{stream} render"] = suite_collector("mftcn5", sizes, steps, task, render_only=True)
    rates = collect(collectors, sizes)
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


_FULL_SCALE = (("encoder.model.base.resize", 1.0),)  # the base on the 160x160 frames as rendered
_HEADS = {pool: (("encoder.model.spatial_pool", pool),) for pool in ("mean", "mean+softargmax")}


def bench_ppo_pixels_160(sizes: Sizes) -> list[BenchRow]:
    """PPO collection frames/s on mfTCN5 embeddings at 160x160 (swingup-160, whose spec scales the base's input
    by 0.6): against the same loop rendering only (the target, as at 96x48), against the base on the frames at
    full scale (what the scaling saves), and the head with a spatial soft-argmax beside its mean against the
    mean alone (what the soft-argmax costs)."""
    one_thread()
    steps = sizes.ppo_pixel_steps
    rates = collect({"scaled": suite_collector("mftcn5", sizes, steps, "swingup-160"),
                     "render": suite_collector("mftcn5", sizes, steps, "swingup-160", render_only=True),
                     "full": suite_collector("mftcn5", sizes, steps, "swingup-160", overrides=_FULL_SCALE),
                     **{pool: suite_collector("mftcn5", sizes, steps, "swingup-160", overrides=heads)
                        for pool, heads in _HEADS.items()}}, sizes)
    figure = f"PPO collection on mfTCN5 embeddings, 160x160, base input scaled 0.6 ({sizes.ppo_envs} envs)"
    note = "1 rendered 160x160 frame and 1 base pass on it scaled to 96x96 per agent step (action repeat 8)"
    return [BenchRow(figure, rates["scaled"], "frames/s", "the same loop, rendering only", rates["render"],
                     rates["scaled"] / rates["render"], Target(">=", 0.7), note),
            BenchRow(figure, rates["scaled"], "frames/s", "the base at full scale (160x160)", rates["full"],
                     rates["scaled"] / rates["full"], Target("report"), note),
            BenchRow(figure.replace("scaled 0.6", "scaled 0.6, soft-argmax beside the mean"),
                     rates["mean+softargmax"], "frames/s", "the head's mean alone", rates["mean"],
                     rates["mean+softargmax"] / rates["mean"], Target("report"), note)]


def bench_ppo_state(sizes: Sizes) -> list[BenchRow]:
    """PPO collection frames/s on true state: SuiteBatchEnv + Collector (action repeat 8) against a
    SerialEnv of DMControlEnv + Collector with torchrl's default frame_skip 1, and with frame_skip 8 (the
    same action repeat), all with `ppo_envs` environments."""
    one_thread()
    rates = collect({"ours": suite_collector("true-state", sizes, sizes.ppo_state_steps),
                      "skip1": _serial_collector(sizes, 1), "skip8": _serial_collector(sizes, 8)}, sizes)
    figure = f"PPO collection on true state ({sizes.ppo_envs} envs, action repeat 8)"
    serial = f"torchrl SerialEnv of {sizes.ppo_envs} DMControlEnv"
    return [BenchRow(figure, rates["ours"], "frames/s", f"{serial} (frame_skip 1, its default)", rates["skip1"],
                     rates["ours"] / rates["skip1"], Target(">=", 2)),
            BenchRow(figure, rates["ours"], "frames/s", f"{serial} (frame_skip 8, as ours)", rates["skip8"],
                     rates["ours"] / rates["skip8"], Target(">=", 2))]
