"""Many dm_control suite environments stepped together in one process, as one batched torchrl environment.

torchrl's SerialEnv / ParallelEnv collect 400-850 frames/s here (one Python env object and a tensordict
round trip per instance per step); stepping a list of dm_control physics instances inside one
`EnvBase` with a batch dimension removes that overhead. Every instance runs episodes of the same fixed
length (the suite's cartpole and cheetah never terminate early; a task that does is refused when it
first terminates), so all of them start and end episodes together and a reset always resets the whole
batch.

Each agent step applies the action for `action_repeat` physics steps and sums the rewards (returns stay
on the suite's 1000-step scale). This environment only simulates and renders: what the policy sees is made
by transforms (`rl/observation.py`). It emits, for each agent step, the last `stream_frames` frames of the
encoder's stream that fell inside it, oldest first: "state" [E, k, S] (the simulator state, always) and
"frames" [E, k, H, W, 3] (uint8, only when `renders`). The stream has the frame rate of the encoder's
training data: a frame every `frame_every` physics steps (the data set's `action_repeat`), so only the
frames a clip can reach are ever rendered. A reset emits the episode's first frame k times (a clip before
an episode's first frame repeats it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from mftcn_bench.core.errors import SpecError, TrainingError
from mftcn_bench.sim.rendering import MultiViewRenderer, RenderSettings, ensure_gl


@dataclass(frozen=True)
class SuiteConfig:
    """Which suite task, how it is seen and how it is stepped: the task spec's `[env]` table, with the
    image size, render settings and frame rate of its `[dataset]` (frames look like the encoder's data)."""

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
    def agent_steps(self) -> int:
        return self.episode_length // self.action_repeat

    @property
    def frames_per_step(self) -> int:
        """Frames of the encoder's stream in one agent step."""
        return self.action_repeat // self.frame_every


def physics_state(physics, domain: str) -> np.ndarray:
    """The true state recorded with each frame: cartpole (x, theta, x_dot, theta_dot); other domains
    the suite's observation of positions and velocities without the horizontal root position (which
    is not observable from a tracking camera and not part of the suite's observation)."""
    qpos, qvel = physics.data.qpos, physics.data.qvel
    if domain == "cartpole":
        return np.concatenate([qpos, qvel])
    return np.concatenate([qpos[1:], qvel])


class SuiteBatchEnv(EnvBase):
    """`num_envs` instances of a suite task with a batch dimension: physics, rewards and the stream's frames."""

    def __init__(self, config: SuiteConfig, num_envs: int, seed: int, stream_frames: int = 1,
                 renders: bool = False) -> None:
        super().__init__(batch_size=torch.Size([num_envs]))
        ensure_gl()
        from dm_control import suite
        from dm_control.rl.control import compute_n_steps

        if not 1 <= stream_frames <= config.frames_per_step:
            raise ValueError(f"stream_frames must be in 1..{config.frames_per_step} (the stream's frames in one "
                             f"agent step), got {stream_frames}")
        self.config, self.num_envs, self.seed = config, num_envs, seed
        self.stream_frames, self.renders = stream_frames, renders
        self.episode_index = 0  # episodes started so far by each instance; seeds the next initial states
        self._envs = [suite.load(config.domain, config.task, task_kwargs={"random": seed}) for _ in range(num_envs)]
        first = self._envs[0]
        # dm_control's own Environment.step also builds an observation dict (about a fifth of a true-state
        # rollout, never read here); the public task and physics API does the rest of it.
        self._substeps = compute_n_steps(first.control_timestep(), first.physics.timestep())
        self._renderers = [MultiViewRenderer(env.physics, [config.camera], config.height, config.width,
                                             config.render) for env in self._envs] if renders else []
        self._t = 0
        k = stream_frames
        state_dim = physics_state(first.physics, config.domain).shape[0]
        observed = {"state": Unbounded(shape=(num_envs, k, state_dim), dtype=torch.float64)}
        if renders:
            observed["frames"] = Bounded(0, 255, shape=(num_envs, k, config.height, config.width, 3),
                                         dtype=torch.uint8)
        self.observation_spec = Composite(observed, shape=(num_envs,))
        action_dim = int(first.action_spec().shape[0])
        self.action_spec = Bounded(-1.0, 1.0, shape=(num_envs, action_dim), dtype=torch.float32)
        self.reward_spec = Unbounded(shape=(num_envs, 1), dtype=torch.float32)
        flag = Categorical(2, shape=(num_envs, 1), dtype=torch.bool)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=(num_envs,))

    def _frame(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The state [E, S] and (when rendering) the frame [E, H, W, 3] of the current physics step."""
        state = np.stack([physics_state(env.physics, self.config.domain) for env in self._envs])
        frames = np.stack([renderer.render()[0] for renderer in self._renderers]) if self.renders else None
        return state, frames

    def _observation(self, states: list[np.ndarray], frames: list[np.ndarray | None]) -> dict[str, torch.Tensor]:
        out = {"state": torch.from_numpy(np.stack(states, axis=1))}
        if self.renders:
            out["frames"] = torch.from_numpy(np.stack(frames, axis=1))
        return out

    def _physics_step(self, env, action: np.ndarray) -> float:
        """One control step of a suite environment, as dm_control's `Environment.step` without its
        observation; the episode's length is this environment's, so the suite's own time limit never acts."""
        env.task.before_step(action, env.physics)
        env.physics.step(self._substeps)
        env.task.after_step(env.physics)
        if env.task.get_termination(env.physics) is not None:
            raise TrainingError(f"{self.config.domain}-{self.config.task} ended an episode early (the task "
                                f"terminated); the batched environment runs fixed-length episodes of tasks that "
                                f"never terminate (cartpole, cheetah)")
        return env.task.get_reward(env.physics) or 0.0

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
        state, frames = self._frame()
        done = torch.zeros((self.num_envs, 1), dtype=torch.bool)
        observed = self._observation([state] * self.stream_frames, [frames] * self.stream_frames)
        return TensorDict({**observed, "done": done, "terminated": done.clone(), "truncated": done.clone()},
                          batch_size=self.batch_size)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = np.clip(tensordict.get("action").detach().cpu().numpy().astype(np.float64), -1.0, 1.0)
        every, frames_per_step = self.config.frame_every, self.config.frames_per_step
        first_kept = frames_per_step - self.stream_frames + 1  # the stream's frames 1..frames_per_step
        reward = np.zeros(self.num_envs, dtype=np.float64)
        states: list[np.ndarray] = []
        frames: list[np.ndarray | None] = []
        for r in range(self.config.action_repeat):
            for i, env in enumerate(self._envs):
                reward[i] += self._physics_step(env, action[i])
            if (r + 1) % every == 0 and (r + 1) // every >= first_kept:
                state, frame = self._frame()
                states.append(state)
                frames.append(frame)
        self._t += 1
        truncated = torch.full((self.num_envs, 1), self._t >= self.config.agent_steps, dtype=torch.bool)
        return TensorDict({**self._observation(states, frames),
                           "reward": torch.from_numpy(reward).float().unsqueeze(-1),
                           "done": truncated.clone(), "terminated": torch.zeros_like(truncated),
                           "truncated": truncated}, batch_size=self.batch_size)

    def _set_seed(self, seed: int | None) -> None:
        """Instances are seeded at construction (from the run's seed); torchrl's seeding is not used."""

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Free every instance's MuJoCo data and rendering contexts (an EGL context each, when rendering)."""
        if not self.is_closed:
            for env in self._envs:
                env.physics.free()
        super().close(raise_if_closed=raise_if_closed)


EnvFactory = Callable[[int, int], EnvBase]  # (num_envs, seed) -> environment (a SuiteBatchEnv, transformed)


def suite_env_of(env: EnvBase) -> SuiteBatchEnv:
    """The `SuiteBatchEnv` under an environment's transforms."""
    from torchrl.envs import TransformedEnv

    base = env.base_env if isinstance(env, TransformedEnv) else env
    if not isinstance(base, SuiteBatchEnv):
        raise TypeError(f"expected a SuiteBatchEnv (transformed or not), got {type(base).__name__}")
    return base
