"""Expert policies for demonstration datasets: PPO on true state, trained once per config and cached.

The cheetah task's encoder only ever sees an expert at work (the paper's protocol). The expert is a PPO
policy trained on the simulator state with the task's `[expert_ppo]` settings; it is kept under the
home's `experts/<key>/` (key: a hash of the environment, PPO settings and seed), trained under a lock
so concurrent runs train it once, and resumed from its checkpoint after a kill.
"""

from __future__ import annotations

import io
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from mftcn_bench.core import identity
from mftcn_bench.core.errors import TrainingError
from mftcn_bench.core.fileio import atomic_write_bytes, exclusive_lock
from mftcn_bench.rl.observation import observed_env
from mftcn_bench.rl.observers import StateObserver
from mftcn_bench.rl.ppo import PolicyNetworks, PPOConfig, evaluate_policy, train_ppo
from mftcn_bench.rl.suite_env import SuiteBatchEnv, SuiteConfig

_FRAMES_ONLY = ("camera", "height", "width", "render", "frame_every")  # how frames are seen: an expert sees none


def expert_key(env: SuiteConfig, ppo: PPOConfig, seed: int) -> str:
    """The expert's identity: its environment as the state sees it (not the frames' camera, size, render
    settings or rate, so a change of how demonstrations are filmed keeps the expert), PPO settings, seed."""
    stepped = {k: v for k, v in asdict(env).items() if k not in _FRAMES_ONLY}
    return identity.expert_key(stepped, asdict(ppo), seed)


def state_env_factory(env_config: SuiteConfig):
    """Environments whose observation is the simulator state (nothing rendered)."""
    sizing = SuiteBatchEnv(env_config, 1, 0)
    simulator_dim = sizing.observation_spec["state"].shape[-1]
    sizing.close()
    state_dim = int(StateObserver().push(None, np.ones(1, bool), np.zeros((1, simulator_dim))).shape[1])

    def make_env(num_envs: int, seed: int) -> TransformedEnv:
        return observed_env(env_config, num_envs, seed, StateObserver(), state_dim, False)

    return make_env


def ensure_expert(experts_dir: Path, env_config: SuiteConfig, ppo: PPOConfig, seed: int,
                  progress=lambda *args: None) -> Path:
    """Path of the trained expert (`expert.pt`), training it first if needed."""
    workdir = experts_dir / f"{env_config.domain}-{env_config.task}-{expert_key(env_config, ppo, seed)}"
    path = workdir / "expert.pt"
    if path.exists():
        return path
    workdir.mkdir(parents=True, exist_ok=True)
    with exclusive_lock(experts_dir / f".{workdir.name}.lock"):
        if path.exists():
            return path
        make_env = state_env_factory(env_config)
        nets, state = train_ppo(make_env, ppo, seed, workdir, progress)
        returns = evaluate_policy(make_env, nets, ppo.eval_episodes, min(ppo.num_envs, ppo.eval_episodes), seed)
        buffer = io.BytesIO()
        torch.save({"nets": nets.state_dict()}, buffer)
        summary = {"return_mean": float(returns.mean()), "return_std": float(returns.std(ddof=1)),
                   "episodes": len(returns), "frames": state.frames, "wall_s": state.wall_s,
                   "curve": {"frames": state.curve_frames, "return": state.curve_return}}
        atomic_write_bytes(workdir / "expert.json", json.dumps(summary, indent=1).encode())
        atomic_write_bytes(path, buffer.getvalue())
    return path


class ExpertPolicy:
    """A trained expert's mean action for a single simulator state."""

    def __init__(self, path: Path, env_config: SuiteConfig, ppo: PPOConfig) -> None:
        from torchrl.envs import ExplorationType, set_exploration_type

        env = state_env_factory(env_config)(1, 0)
        self._nets = PolicyNetworks(env, ppo, None)
        env.close()
        try:
            self._nets.load_state_dict(torch.load(path, weights_only=True, map_location="cpu")["nets"])
        except Exception as exc:  # noqa: BLE001 - an unreadable expert gets one line
            raise TrainingError(f"expert policy {path} cannot be read ({type(exc).__name__}); delete its folder "
                                f"to train it again") from None
        self._mode = set_exploration_type(ExplorationType.DETERMINISTIC)

    @torch.no_grad()
    def act(self, state: np.ndarray) -> np.ndarray:
        """The mean action for one simulator state (as `physics_state` records it)."""
        observation = StateObserver().push(None, np.ones(1, bool), np.asarray(state, dtype=np.float64)[None])
        td = TensorDict({"observation": torch.from_numpy(observation)}, batch_size=[1])
        with self._mode:
            return self._nets.policy(td).get("action")[0].double().numpy()
