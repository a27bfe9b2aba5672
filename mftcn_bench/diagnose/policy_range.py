"""Where a finished cartpole run's policy drives the cart, whether its camera sees it there, and how well the
state probe reads what the policy meets.

The encoder and the final PPO networks of a finished run (`mftcn-bench run --encoder E --task T --preset P
--seed S`, its folder `runs/<id>` in the home) are loaded and at least `episodes` test episodes (whole rounds
of up to the task's number of environments) are played with the policy's mean action on the run's own
evaluation environments (its evaluation seeds, so the replayed returns are the record's first test returns).
The simulator state of every frame of the encoder's stream is kept. The answer: the distribution of |x|, how
often the task's camera cuts the cart, misses its centre or the pole's tip (`coverage`), and the state
probe's R^2 on those states: the probe of `state_probe`, fitted on the data set's train split from the task's
camera, scored on the policy's frames (drawn again from the kept states, as the environment draws them).
Whether the square 160x160 image that cuts the cart in most frames of the random-action data also cuts it
where a policy drives it, and whether the embedding carries the state there, are what it was written for.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import ExplorationType, Transform, set_exploration_type

from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.home import BenchHome
from mftcn_bench.data.dataset import find_dataset
from mftcn_bench.diagnose.coverage import CartRange, CoverageFractions, cartpole_physics, coverage
from mftcn_bench.diagnose.state_probe import ProbeScore, dimension_names, fit_camera_probe, probe_config, score
from mftcn_bench.encoders.base import Encoder
from mftcn_bench.rl.ppo import EVAL_SEED_OFFSET, PolicyNetworks
from mftcn_bench.rl.suite_env import SuiteConfig, suite_env_of
from mftcn_bench.run.artifacts import build_encoder, prepare_dataset
from mftcn_bench.run.plan import PreparedRun, RunRequest, prepare_with_encoder, run_id_of
from mftcn_bench.sim.rendering import MultiViewRenderer, ensure_gl
from mftcn_bench.tasks.control import PPOTask


@dataclass(frozen=True)
class PolicyRange:
    """`replay_policy`'s answer. `returns_stored` are the record's first test returns, as many as it has up to
    the episodes replayed. `probe_test` is the state probe's R^2 on the data set's test split and `probe` on
    the policy's frames; both None when the encoder's stream skips frames of the data set's rate (the probe's
    e_t - e_{t-1} would span other intervals than in its training data), and `probe_note` says so."""

    encoder: str
    task: str
    preset: str
    seed: int
    run_id: str
    returns_replayed: tuple[float, ...]
    returns_stored: tuple[float, ...]
    frames: int
    cart: CartRange
    camera: CoverageFractions
    width: int
    height: int
    dimensions: tuple[str, ...]
    probe_test: ProbeScore | None
    probe: ProbeScore | None
    probe_note: str = ""

    @property
    def episodes(self) -> int:
        return len(self.returns_replayed)


class StateRecorder(Transform):
    """Keeps the simulator state of every frame of the stream an environment emits ([E, k, S] a step)."""

    def __init__(self) -> None:
        super().__init__(in_keys=[], out_keys=[])
        self.states: list[np.ndarray] = []

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # a reset repeats its first frame to fill the stream's k; the episode has it once
        self.states.append(tensordict_reset.get("state")[:, -1:].numpy().copy())
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self.states.append(next_tensordict.get("state").numpy().copy())
        return next_tensordict

    def episodes(self) -> list[np.ndarray]:
        """The states [T, S] of each environment's episode since the last call, in environment order."""
        stacked = np.concatenate(self.states, axis=1)  # [E, T, S]
        self.states = []
        return list(stacked)


def render_states(config: SuiteConfig, episodes: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The task camera's frames [T, H, W, 3] of each episode's cartpole states [T, 4], drawn by the task's own
    suite model at its size and render settings, as its environment draws them."""
    ensure_gl()  # dm_control picks its GL back end when it is imported
    from dm_control import suite

    physics = suite.load(config.domain, config.task).physics
    renderer = MultiViewRenderer(physics, [config.camera], config.height, config.width, config.render)
    drawn = []
    for states in episodes:
        frames = np.empty((len(states), config.height, config.width, 3), dtype=np.uint8)
        for t, state in enumerate(states):
            physics.data.qpos[:], physics.data.qvel[:] = state[:2], state[2:4]
            physics.forward()
            frames[t] = renderer.render()[0]
        drawn.append(frames)
    return drawn


def _checked(request: RunRequest, episodes: int) -> tuple[PreparedRun, Encoder | None, PPOTask]:
    if episodes < 1:
        raise SpecError(f"--episodes must be >= 1, got {episodes}")
    prepared, untrained = prepare_with_encoder(request)
    task = prepared.task
    if not isinstance(task, PPOTask) or task.env_config.domain != "cartpole":
        raise SpecError(f"diagnose policy needs a cartpole control task (swingup, swingup-160, ...); "
                        f"{request.task!r} is not one")
    return prepared, untrained, task


def replay_policy(request: RunRequest, home: BenchHome, episodes: int = 8,
                  show_progress: bool = False) -> PolicyRange:
    """Replay the stored policy of `request`'s finished run on at least `episodes` of its test episodes."""
    prepared, untrained, task = _checked(request, episodes)
    command = (f"mftcn-bench run --encoder {request.encoder} --task {request.task} --preset {prepared.preset} "
               f"--seed {request.seed}")
    dataset = None
    if prepared.reads_data:  # the run's id holds its data set's fingerprint; without the data there is no run
        dataset = find_dataset(home.datasets, task.dataset_config, task.collector)
        if dataset is None:
            raise BenchError(f"no finished run of {request.encoder} on {request.task} (preset {prepared.preset}, "
                             f"seed {request.seed}) in {home.root}: its data set is not there; run `{command}` "
                             f"first (with the code that made it)")
    run_dir = home.runs / run_id_of(prepared, None if dataset is None else dataset.fingerprint)
    checkpoint = run_dir / "ppo_checkpoint.pt"
    if not (run_dir / "result.json").exists():
        raise BenchError(f"no finished run of {request.encoder} on {request.task} (preset {prepared.preset}, seed "
                         f"{request.seed}): its run folder {run_dir} is missing or unfinished (no result.json); run "
                         f"`{command}` first (with the code that made it)")
    if not checkpoint.exists():
        raise BenchError(f"run {run_dir.name} of {request.encoder} on {request.task} has no PPO checkpoint "
                         f"({checkpoint} is missing): `{command}` makes one in a home without this run (where the "
                         f"run is stored, its result is reused, not computed again)")
    encoder, _ = build_encoder(prepared, dataset, home, show_progress=show_progress, untrained=untrained)
    # The run's own environment factory, so that the replay sees exactly what the policy saw.
    make_env, trunk = task.env_factory(encoder)
    env = make_env(min(task.ppo.num_envs, episodes), request.seed + EVAL_SEED_OFFSET)
    nets = PolicyNetworks(env, task.ppo, trunk)
    try:
        nets.load_state_dict(torch.load(checkpoint, map_location="cpu", weights_only=True)["nets"])
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint gets the same one-line answer
        env.close()
        raise BenchError(f"PPO checkpoint {checkpoint} cannot be read ({type(exc).__name__}); `{command}` makes "
                         f"a readable one in a home without this run") from None
    recorder = StateRecorder()
    env.transform.insert(0, recorder)
    suite = suite_env_of(env)
    # The probe's features difference consecutive frames of the data set's rate: a stream that emits fewer
    # frames a step than the data set has (a short lookback on a physics-rate task) cannot give them.
    whole_stream = suite.stream_frames == suite.config.frames_per_step
    returns: list[float] = []
    visited: list[np.ndarray] = []
    try:
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            while len(returns) < episodes:
                rollout = env.rollout(suite.config.agent_steps, nets.policy, break_when_any_done=False)
                returns.extend(rollout.get(("next", "reward")).sum(dim=(1, 2)).double().tolist())
                visited.extend(recorder.episodes())
    finally:
        env.close()
    returns, visited = returns[:episodes], visited[:episodes]
    states = np.concatenate(visited)
    record = json.loads((run_dir / "result.json").read_text())
    stored = record["curves"]["test"]["return"][:episodes]
    config = task.env_config
    seen = CoverageFractions.of(config.camera, coverage(cartpole_physics(), config.camera, config.height,
                                                        config.width, states))

    probe_test = probe = None
    note = ""
    if whole_stream:
        probe_test, probe = _probe_on_policy(prepared, home, encoder, config, visited, show_progress)
    else:
        note = (f"no probe on the policy's states: the stream emits {suite.stream_frames} of the "
                f"{suite.config.frames_per_step} frames of the data set's rate in an agent step")
    return PolicyRange(request.encoder, request.task, prepared.preset, request.seed, run_dir.name, tuple(returns),
                       tuple(float(r) for r in stored), len(states), CartRange.of(states), seen, config.width,
                       config.height, dimension_names(states.shape[1]), probe_test, probe, note)


def _probe_on_policy(prepared: PreparedRun, home: BenchHome, encoder: Encoder, config: SuiteConfig,
                     visited: Sequence[np.ndarray], show_progress: bool) -> tuple[ProbeScore, ProbeScore]:
    """The probe of the task camera's embedding, fitted on the data set's train split: its R^2 on the test
    split and on the policy's episodes (frames drawn from their states)."""
    # The probe reads the task's data whatever the encoder (a run of true state on swing-up reads none).
    dataset = prepare_dataset(replace(prepared, reads_data=True), home, show_progress=show_progress)
    fitted = fit_camera_probe(encoder, dataset, config.camera, probe_config(prepared), prepared.request.seed)
    view = dataset.cameras.index(config.camera)
    test = score(fitted, encoder, ((e.frames[view], e.state) for e in dataset.iter_episodes("test")))
    on_policy = score(fitted, encoder, zip(render_states(config, visited), visited, strict=True))
    return test, on_policy
