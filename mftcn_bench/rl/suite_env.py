"""Many dm_control suite environments stepped together in one process, as one batched torchrl environment.

torchrl's SerialEnv / ParallelEnv collect 400-850 frames/s here (one Python env object and a tensordict
round trip per instance per step); stepping a list of dm_control physics instances inside one
`EnvBase` with a batch dimension removes that overhead. Every instance runs episodes of the same fixed
length (the suite's cartpole and cheetah never terminate early), so all of them start and end episodes
together and a reset always resets the whole batch.

Each agent step applies the action for `action_repeat` physics steps and sums the rewards (returns stay
on the suite's 1000-step scale). The policy's input is an observer's output (`observers.py`): the
frozen encoder's embedding of the clip ending at the current frame. The encoder's stream of frames has
the frame rate of its training data: a frame every `frame_every` physics steps (the data set's
`action_repeat`: 1 is the simulator's rate, `action_repeat` of the environment is one frame per agent
step, as pixel-RL code on the suite renders). Frames are rendered only when the encoder reads pixels, and
then only those a clip can reach: the last min(lookback, frames per agent step) of each agent step, so a
clip sees frames exactly as far apart as in the encoder's training data. With `embedding_difference` the
observation is [e_t, e_t - e_{t-1}], e_{t-1} the embedding of the stream's frame before (0 difference at
an episode's first frame, as the probe's clamping). A
`Readout` maps that observation once more before the policy sees it (swingup-probe-state: the state a
fitted probe predicts from it). For an
encoder trained jointly with the policy (pixels-cnn) the environment emits the raw
clip ("pixels", uint8 [E, n, 3, H, W]) instead.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from mftcn_bench.core.errors import SpecError
from mftcn_bench.data.clips import ClipRing
from mftcn_bench.rl.observers import Observer
from mftcn_bench.sim.rendering import MultiViewRenderer, RenderSettings, ensure_gl


@dataclass(frozen=True)
class SuiteConfig:
    """Which suite task, how it is seen and how it is stepped: the task spec's `[env]` table, with the
    image size and render settings of its `[dataset]` (frames look like the encoder's training data)."""

    domain: str
    task: str
    camera: str
    height: int
    width: int
    episode_length: int  # physics steps per episode
    action_repeat: int
    render: RenderSettings
    frame_every: int     # physics steps between two frames of the encoder's stream (its data set's)
    # The policy sees [e_t, e_t - e_{t-1}] (the probe's input; e_{t-1}: the embedding of the stream's
    # frame before) instead of e_t alone.
    embedding_difference: bool = False

    def __post_init__(self) -> None:
        if self.action_repeat < 1 or self.episode_length % self.action_repeat:
            raise SpecError(f"[env] episode_length ({self.episode_length}) must be a positive multiple of "
                            f"action_repeat ({self.action_repeat})")
        if self.frame_every < 1 or self.action_repeat % self.frame_every:
            raise SpecError(f"[env] action_repeat ({self.action_repeat}) must be a multiple of the data set's "
                            f"action_repeat ({self.frame_every}): the encoder's frames come that many physics "
                            f"steps apart")

    @property
    def frames_per_step(self) -> int:
        """Frames of the encoder's stream in one agent step."""
        return self.action_repeat // self.frame_every

    @property
    def agent_steps(self) -> int:
        return self.episode_length // self.action_repeat


def physics_state(physics, domain: str) -> np.ndarray:
    """The true state recorded with each frame: cartpole (x, theta, x_dot, theta_dot); other domains
    the suite's observation of positions and velocities without the horizontal root position (which
    is not observable from a tracking camera and not part of the suite's observation)."""
    qpos, qvel = physics.data.qpos, physics.data.qvel
    if domain == "cartpole":
        return np.concatenate([qpos, qvel])
    return np.concatenate([qpos[1:], qvel])


def step_reward(env, action: np.ndarray) -> float:
    """One step of a dm_control suite environment: dm_control's `Environment.step` (control, physics steps,
    reward, step count, the reset after the time limit) without building the observation, which this module
    never reads (it records `physics_state`); the observation was about a fifth of a true-state rollout's
    time (benchmarks/bench_ppo.py)."""
    if env._reset_next_step:
        env.reset()
        return 0.0
    env._task.before_step(action, env._physics)
    env._physics.step(env._n_sub_steps)
    env._task.after_step(env._physics)
    reward = env._task.get_reward(env._physics)
    env._step_count += 1
    if env._step_count >= env._step_limit or env._task.get_termination(env._physics) is not None:
        env._reset_next_step = True
    return reward or 0.0


class Readout(Protocol):
    """A fixed map from the environment's observation rows [E, F] to what the policy sees, [E, out_features]
    (not trained by PPO)."""

    out_features: int

    def __call__(self, observation: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class PixelClip:
    """Emit the raw clip of `frames` frames at `stride` (for encoders trained with the policy)."""

    frames: int
    stride: int


class SuiteBatchEnv(EnvBase):
    """`num_envs` instances of a suite task with a batch dimension; observation = observer embedding."""

    def __init__(self, config: SuiteConfig, num_envs: int, seed: int,
                 observer: Observer | None, embedding_dim: int, observer_uses_pixels: bool,
                 lookback: int = 1, pixel_clip: PixelClip | None = None,
                 readout: Readout | None = None) -> None:
        super().__init__(batch_size=torch.Size([num_envs]))
        ensure_gl()
        from dm_control import suite

        if (observer is None) == (pixel_clip is None):
            raise ValueError("give exactly one of observer and pixel_clip")
        self.config, self.num_envs = config, num_envs
        self.observer, self.pixel_clip, self.readout = observer, pixel_clip, readout
        self.seed = seed
        self.episode_index = 0  # episodes started so far by each instance; seeds the next initial states
        self._envs = [suite.load(config.domain, config.task, task_kwargs={"random": seed}) for _ in range(num_envs)]
        self._renders = observer_uses_pixels or pixel_clip is not None
        self._renderers = [MultiViewRenderer(env.physics, [config.camera], config.height, config.width,
                                             config.render)
                           for env in self._envs] if self._renders else []
        if pixel_clip is not None:  # the raw clip of channel-first frames [E, lookback, 3, H, W]
            self._window = ClipRing(pixel_clip.frames, pixel_clip.stride, num_envs)
            lookback = self._window.lookback
        self.lookback = lookback
        if config.embedding_difference and pixel_clip is not None:
            raise SpecError("[env] embedding_difference needs an encoder's embedding; an encoder trained with "
                            "the policy (pixels-cnn) gives the policy raw clips")
        if readout is not None and pixel_clip is not None:
            raise SpecError("a readout maps an encoder's embedding; an encoder trained with the policy (pixels-cnn) "
                            "gives the policy raw clips")
        self._embedded_steps = 2 if config.embedding_difference and config.frames_per_step > 1 else 1
        reach = max(lookback, self._embedded_steps)
        self.render_steps = min(reach, config.frames_per_step) if self._renders else 0  # frames per agent step
        self._previous: np.ndarray | None = None  # e_{t-1} from inside the action repeat
        self._last: np.ndarray | None = None      # the last agent step's embedding (e_{t-1} at action repeat 1)
        self._t = 0
        action_dim = int(self._envs[0].action_spec().shape[0])
        width = readout.out_features if readout is not None else embedding_dim * (
            2 if config.embedding_difference else 1)
        obs_spec = (Unbounded(shape=(num_envs, width), dtype=torch.float32) if pixel_clip is None else
                    Bounded(0, 255, shape=(num_envs, pixel_clip.frames, 3, config.height, config.width),
                            dtype=torch.uint8))
        self._obs_key = "observation" if pixel_clip is None else "pixels"
        self.observation_spec = Composite({self._obs_key: obs_spec}, shape=(num_envs,))
        self.action_spec = Bounded(-1.0, 1.0, shape=(num_envs, action_dim), dtype=torch.float32)
        self.reward_spec = Unbounded(shape=(num_envs, 1), dtype=torch.float32)
        flag = Categorical(2, shape=(num_envs, 1), dtype=torch.bool)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=(num_envs,))

    # -- observation of the current frame -------------------------------------------------------------
    def _frames(self) -> np.ndarray | None:
        if not self._renders:
            return None
        return np.stack([renderer.render()[0] for renderer in self._renderers])

    def _state(self) -> np.ndarray:
        return np.stack([physics_state(env.physics, self.config.domain) for env in self._envs])

    def _observe(self, start: bool, embed: bool = True) -> torch.Tensor | None:
        """The observation of the current frame; with `embed` False the frame only enters the clip
        history (an inner step of an action repeat, whose observation nobody reads)."""
        frames = self._frames()
        if self.pixel_clip is not None:
            self._window.push(np.ascontiguousarray(frames.transpose(0, 3, 1, 2)), np.full(self.num_envs, start))
            return torch.from_numpy(self._window.clip()) if embed else None
        starts = np.full(self.num_envs, start)
        if not embed:
            self.observer.observe(frames, starts, self._state())
            return None
        out = self.observer.push(frames, starts, self._state())
        if self.config.embedding_difference:
            previous = out if start else self._previous if self._previous is not None else self._last
            self._previous, self._last = None, out
            out = np.concatenate([out, out - previous], axis=1)
        if self.readout is not None:
            out = np.ascontiguousarray(self.readout(out), dtype=np.float32)
        return torch.from_numpy(out)

    def _remember(self) -> None:
        """Embed the frame before an agent step's last one: e_{t-1} of the difference."""
        frames = self._frames()
        self._previous = self.observer.push(frames, np.zeros(self.num_envs, bool), self._state())

    # -- torchrl EnvBase ------------------------------------------------------------------------------
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(-1)
            if not bool(mask.all()):
                raise RuntimeError("SuiteBatchEnv resets all its environments together (fixed-length episodes)")
        for i, env in enumerate(self._envs):  # initial state from (seed, instance, episode number)
            env.task._random = np.random.RandomState(np.random.SeedSequence([self.seed, i, self.episode_index])
                                                     .generate_state(1)[0])
            env.reset()
        self.episode_index += 1
        self._t = 0
        obs = self._observe(start=True)
        done = torch.zeros((self.num_envs, 1), dtype=torch.bool)
        return TensorDict({self._obs_key: obs, "done": done, "terminated": done.clone(),
                           "truncated": done.clone()}, batch_size=self.batch_size)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = np.clip(tensordict.get("action").detach().cpu().numpy().astype(np.float64), -1.0, 1.0)
        every, frames = self.config.frame_every, self.config.frames_per_step
        reward = np.zeros(self.num_envs, dtype=np.float64)
        obs = None
        for r in range(self.config.action_repeat):
            for i, env in enumerate(self._envs):
                reward[i] += step_reward(env, action[i])
            if (r + 1) % every:
                continue  # between two frames of the stream
            frame = (r + 1) // every  # 1 ... frames
            if frame == frames:
                obs = self._observe(start=False)
            elif frame == frames - 1 and self._embedded_steps == 2:
                self._remember()
            elif frame > frames - self.render_steps:
                self._observe(start=False, embed=False)
        self._t += 1
        truncated = torch.full((self.num_envs, 1), self._t >= self.config.agent_steps, dtype=torch.bool)
        return TensorDict({self._obs_key: obs, "reward": torch.from_numpy(reward).float().unsqueeze(-1),
                           "done": truncated.clone(), "terminated": torch.zeros_like(truncated),
                           "truncated": truncated}, batch_size=self.batch_size)

    def _set_seed(self, seed: int | None) -> None:
        """Instances are seeded at construction (from the run's seed); torchrl's seeding is not used."""


EnvFactory = Callable[[int, int], SuiteBatchEnv]  # (num_envs, seed) -> environment
