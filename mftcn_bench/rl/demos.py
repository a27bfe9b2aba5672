"""Multi-view demonstration videos: an expert policy's episodes recorded from several cameras.

Each episode starts from the suite's own random initial state (seeded by the dataset seed and the episode
index) and follows the expert's mean action, held for the environment's action repeat. A frame is rendered
from all cameras every `[dataset] action_repeat` simulator steps (the encoder's stream: 1, every step; the
environment's action repeat, every agent step), with its true state and the expert's action then.

With `action_noise` > 0 in the data set's config the environment is driven by the expert's action plus
Gaussian noise of that standard deviation (clipped to the action bounds) while the expert's own action is
what is recorded: DART (Laskey et al., 2017), so that a clone learns how the expert recovers from the states
its own small errors lead to. Without the key the episodes are the expert's alone.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from mftcn_bench.rl.expert import ExpertPolicy
from mftcn_bench.rl.ppo import PPOConfig
from mftcn_bench.rl.suite_env import SuiteConfig, physics_state
from mftcn_bench.sim.rendering import MultiViewRenderer, RenderSettings, ensure_gl


class StatePolicy(Protocol):
    """What the collector records: an action for a simulator state."""

    def act(self, state: np.ndarray) -> np.ndarray: ...


class ExpertDemoCollector:
    """`collector(config, index)` for `ensure_dataset`, recording the expert stored at `expert_path`, or
    `policy` instead when one is given (e.g. random actions, to see states the demonstrations never visit).
    Without either it still names the dataset's code (its identity) but cannot collect."""

    def __init__(self, expert_path: Path | None, env_config: SuiteConfig, ppo: PPOConfig,
                 policy: StatePolicy | None = None) -> None:
        self.expert_path, self.env_config, self.ppo = expert_path, env_config, ppo
        self._expert: StatePolicy | None = policy

    def __call__(self, config: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
        ensure_gl()
        from dm_control import suite

        if self._expert is None:
            if self.expert_path is None:
                raise RuntimeError("the expert must be trained (Task.prepare_artifacts) before its demos are recorded")
            self._expert = ExpertPolicy(self.expert_path, self.env_config, self.ppo)
        rng = np.random.default_rng([int(config["seed"]), index])
        env = suite.load(config["domain"], self.env_config.task, task_kwargs={"random": int(rng.integers(2**31))})
        physics = env.physics
        renderer = MultiViewRenderer(physics, config["cameras"], int(config["height"]), int(config["width"]),
                                     RenderSettings.from_table(f"dataset {config['name']!r}", config["render"]))
        env.reset()
        length, every = int(config["episode_length"]), int(config["action_repeat"])  # frames; steps apart
        repeat = self.env_config.action_repeat
        frames = np.empty((len(config["cameras"]), length, int(config["height"]), int(config["width"]), 3),
                          dtype=np.uint8)
        state_dim = physics_state(physics, config["domain"]).shape[0]
        state = np.empty((length, state_dim), dtype=np.float64)
        action = np.empty((length, int(env.action_spec().shape[0])), dtype=np.float32)
        noise = float(config.get("action_noise", 0.0))
        current = applied = np.zeros(action.shape[1])
        for step in range(length * every):
            t, filmed = divmod(step, every)
            if step % repeat == 0:
                current = self._expert.act(physics_state(physics, config["domain"]))
                applied = np.clip(current + noise * rng.standard_normal(current.shape), -1.0, 1.0) if noise else current
            if filmed == 0:
                frames[:, t] = renderer.render()
                state[t] = physics_state(physics, config["domain"])
                action[t] = current
            env.step(applied)
        return {"frames": frames, "state": state, "action": action}
