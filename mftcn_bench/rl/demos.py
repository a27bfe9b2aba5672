"""Multi-view demonstration videos: an expert policy's episodes recorded from several cameras.

Each episode starts from the suite's own random initial state (seeded by the dataset seed and the episode
index) and follows the expert's mean action, held for the environment's action repeat. A frame is rendered
from all cameras every `[dataset] action_repeat` simulator steps (the encoder's stream: 1, every step; the
environment's action repeat, every agent step), with its true state and the expert's action then.

With `action_noise` > 0 in the data set's config the environment is driven by the expert's action plus
Gaussian noise of that standard deviation (clipped to the action bounds) while the expert's own action is
what is recorded: DART (Laskey et al., 2017), so that a clone learns how the expert recovers from the states
its own small errors lead to. Without the key the episodes are the expert's alone.

Pinned demonstrations: the expert's weights alone do not fix the episodes on every CPU (a policy's matrix
products and so the chaotic cheetah's trajectory differ between CPU families), so the project commits the
episodes themselves, each filmed frame's full simulator state and the expert's action, beside the expert
(`record_demos`, `mftcn-bench expert demos`). A data set with such a file renders its frames from those states
(`ExpertDemoCollector` with `demos`), runs no policy and no physics step, and names the file's checksum.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.core.progress import progress_bar
from mftcn_bench.core.provenance import content_hash, file_sha256, versions
from mftcn_bench.rl.expert import ExpertPolicy, ExpertSetup, checked_pinned, pinned_expert
from mftcn_bench.rl.ppo import PPOConfig
from mftcn_bench.rl.suite_env import SuiteConfig, physics_state
from mftcn_bench.sim.rendering import MultiViewRenderer, RenderSettings, ensure_gl

# The data set keys that decide the episodes' states and actions; the rest (cameras, size, render settings,
# episode counts) only say how, and how many of them, are filmed.
_STEPPING = ("domain", "seed", "episode_length", "action_repeat", "action_noise")
REMAKE_DEMOS = "mftcn-bench expert demos"


class StatePolicy(Protocol):
    """What the collector records: an action for a simulator state."""

    def act(self, state: np.ndarray) -> np.ndarray: ...


def _stepping(dataset_config: Mapping[str, Any]) -> dict[str, Any]:
    return {key: dataset_config.get(key, 0.0 if key == "action_noise" else None) for key in _STEPPING}


def pinned_demos_path(expert: ExpertSetup, dataset_config: Mapping[str, Any],
                      folder: Path | None = None) -> Path | None:
    """Where the pinned demonstrations of `expert` (a pinned file) stepped as `dataset_config` are (beside
    the expert's file, or in `folder`), whether or not they exist; None for an expert trained in the home
    (its demonstrations are not pinned)."""
    weights = pinned_expert(expert.env, expert.ppo, expert.seed)
    if weights is None:
        return None
    key = content_hash({"expert": file_sha256(weights), "stepping": _stepping(dataset_config)})
    return (folder or weights.parent) / f"{expert.env.domain}-{expert.env.task}-demos-{key}.npz"


def pinned_demos(expert: ExpertSetup, dataset_config: Mapping[str, Any]) -> Path | None:
    """The committed demonstrations for this expert and stepping, their checksum checked; None if none."""
    path = pinned_demos_path(expert, dataset_config)
    return checked_pinned(path, "pinned demonstrations", REMAKE_DEMOS) if path and path.exists() else None


def recorded_config(expert: ExpertSetup, dataset_config: Mapping[str, Any]) -> dict[str, Any]:
    """A demonstrations data set's config as its key sees it: the expert's identity and, where the project
    pins them, the demonstrations' checksum (another file gives another data set)."""
    demos = pinned_demos(expert, dataset_config)
    pinned = {"demos": f"pinned-{file_sha256(demos)[:16]}"} if demos is not None else {}
    return {**dataset_config, "expert": expert.identity(), **pinned}


def _episode_env(config: Mapping[str, Any], env_config: SuiteConfig, index: int):
    """Episode `index`'s environment, reset, and its generator (the initial state's seed comes first)."""
    from dm_control import suite

    rng = np.random.default_rng([int(config["seed"]), index])
    env = suite.load(config["domain"], env_config.task, task_kwargs={"random": int(rng.integers(2**31))})
    env.reset()
    return env, rng


def _drive(config: Mapping[str, Any], env_config: SuiteConfig, index: int, policy: StatePolicy,
           film: Callable[[int, Any, np.ndarray], None]) -> None:
    """Step episode `index` with `policy` (plus the config's action noise), calling `film(t, physics,
    action)` at each of its `episode_length` frames, before the step from it."""
    env, rng = _episode_env(config, env_config, index)
    physics = env.physics
    length, every = int(config["episode_length"]), int(config["action_repeat"])  # frames; steps apart
    repeat = env_config.action_repeat
    noise = float(config.get("action_noise", 0.0))
    current = applied = np.zeros(int(env.action_spec().shape[0]))
    for step in range(length * every):
        t, filmed = divmod(step, every)
        if step % repeat == 0:
            current = policy.act(physics_state(physics, config["domain"]))
            applied = np.clip(current + noise * rng.standard_normal(current.shape), -1.0, 1.0) if noise else current
        if filmed == 0:
            film(t, physics, current)
        env.step(applied)


class ExpertDemoCollector:
    """`collector(config, index)` for `ensure_dataset`, recording the expert stored at `expert_path`, or
    `policy` instead when one is given (e.g. random actions, to see states the demonstrations never visit),
    or rendering the pinned `demos` (`record_demos`) without running either. Without any of them it still
    names the dataset's code (its identity) but cannot collect."""

    def __init__(self, expert_path: Path | None, env_config: SuiteConfig, ppo: PPOConfig,
                 policy: StatePolicy | None = None, demos: Path | None = None) -> None:
        self.expert_path, self.env_config, self.ppo, self.demos = expert_path, env_config, ppo, demos
        self._expert: StatePolicy | None = policy
        self._episodes: Mapping[str, np.ndarray] | None = None

    def __call__(self, config: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
        ensure_gl()
        length, cameras = int(config["episode_length"]), config["cameras"]
        frames = np.empty((len(cameras), length, int(config["height"]), int(config["width"]), 3), dtype=np.uint8)
        renderer: MultiViewRenderer | None = None
        states: list[np.ndarray] = []
        actions: list[np.ndarray] = []

        def film(t: int, physics: Any, action: np.ndarray) -> None:
            nonlocal renderer
            if renderer is None:
                renderer = MultiViewRenderer(physics, cameras, int(config["height"]), int(config["width"]),
                                             RenderSettings.from_table(f"dataset {config['name']!r}", config["render"]))
            frames[:, t] = renderer.render()
            states.append(physics_state(physics, config["domain"]))
            actions.append(action)

        if self.demos is not None:
            self._replay(config, index, film)
        else:
            _drive(config, self.env_config, index, self._policy(), film)
        return {"frames": frames, "state": np.stack(states), "action": np.stack(actions).astype(np.float32)}

    def _policy(self) -> StatePolicy:
        if self._expert is None:
            if self.expert_path is None:
                raise RuntimeError("the expert must be trained (Task.prepare_artifacts) before its demos are recorded")
            self._expert = ExpertPolicy(self.expert_path, self.env_config, self.ppo)
        return self._expert

    def _replay(self, config: Mapping[str, Any], index: int, film: Callable[[int, Any, np.ndarray], None]) -> None:
        """Film episode `index` of the pinned demonstrations: each frame's simulator state set, not stepped to."""
        if self._episodes is None:
            with np.load(self.demos) as stored:
                self._episodes = {key: stored[key] for key in stored.files}
        qpos, qvel, action = self._episodes["qpos"], self._episodes["qvel"], self._episodes["action"]
        if index >= len(qpos) or qpos.shape[1] < int(config["episode_length"]):
            raise RuntimeError(f"pinned demonstrations {self.demos.name} hold {len(qpos)} episodes of "
                               f"{qpos.shape[1]} frames; episode {index} of {config['episode_length']} frames "
                               f"is not among them: record more with `{REMAKE_DEMOS} --force`")
        env, _ = _episode_env(config, self.env_config, index)
        physics = env.physics
        for t in range(int(config["episode_length"])):
            with physics.reset_context():  # sets the state and recomputes what rendering reads from it
                physics.data.qpos[:] = qpos[index, t]
                physics.data.qvel[:] = qvel[index, t]
            film(t, physics, action[index, t])


def record_demos(expert: ExpertSetup, expert_path: Path, dataset_config: Mapping[str, Any], episodes: int,
                 out: Path, show_progress: bool = True) -> Path:
    """Pin `episodes` demonstrations of `expert` stepped as `dataset_config`: each frame's full simulator
    state (qpos, qvel) and the expert's action, in `out`, with a sidecar (checksum, expert, stepping, CPU)."""
    policy = expert.policy(expert_path)
    length = int(dataset_config["episode_length"])
    qpos: list[np.ndarray] = []
    qvel: list[np.ndarray] = []
    action: list[np.ndarray] = []

    def keep(t: int, physics: Any, act: np.ndarray) -> None:
        qpos.append(physics.data.qpos.copy())
        qvel.append(physics.data.qvel.copy())
        action.append(np.asarray(act, dtype=np.float32))

    with progress_bar(f"demos {expert.env.domain}-{expert.env.task}", "episode", show_progress) as progress:
        for index in range(episodes):
            _drive(dataset_config, expert.env, index, policy, keep)
            progress(index + 1, episodes, {})
    arrays = {name: np.stack(values).reshape(episodes, length, -1)
              for name, values in (("qpos", qpos), ("qvel", qvel), ("action", action))}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, buffer.getvalue())
    sidecar = {"sha256": file_sha256(out), "expert": expert.identity(), "stepping": _stepping(dataset_config),
               "episodes": episodes, "episode_length": length, "versions": versions()}
    atomic_write_bytes(out.with_suffix(".json"), json.dumps(sidecar, indent=1, sort_keys=True).encode())
    return out


def demo_collector(expert: ExpertSetup, expert_path: Path | None, dataset_config: Mapping[str, Any],
                   policy: StatePolicy | None = None) -> ExpertDemoCollector:
    """The collector of a demonstrations data set: the pinned demonstrations where the project has them,
    otherwise `policy` or the expert at `expert_path` (None before the task's artifacts are prepared: it keys
    only)."""
    return ExpertDemoCollector(expert_path, expert.env, expert.ppo, policy,
                               demos=pinned_demos(expert, dataset_config))
