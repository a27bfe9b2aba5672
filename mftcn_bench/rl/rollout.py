"""Whole episodes of a batch of suite environments driven by any action function, and their returns: how
a policy that is no PPO network (a behaviour clone, an expert of single states) is tested."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import step_mdp

from mftcn_bench.rl.suite_env import suite_env_of

Act = Callable[[TensorDictBase], np.ndarray]  # an environment's step data -> actions [E, A]


def rollout_returns(make_env: Callable[[], EnvBase], act: Act, episodes: int) -> np.ndarray:
    """Returns of `episodes` whole episodes of the environments `make_env()` builds, acting by `act`
    (actions clipped to [-1, 1]). Each reset starts every environment from its next initial state
    (`SuiteBatchEnv`), so two policies on environments of one seed and size meet the same initial states in
    the same order."""
    env = make_env()
    steps = suite_env_of(env).config.agent_steps
    returns: list[float] = []
    try:
        with torch.no_grad():
            while len(returns) < episodes:
                td, total = env.reset(), np.zeros(env.batch_size[0])
                for _ in range(steps):
                    td.set("action", torch.from_numpy(np.clip(act(td), -1.0, 1.0).astype(np.float32)))
                    td = env.step(td)
                    total += td.get(("next", "reward")).reshape(-1).double().numpy()
                    td = step_mdp(td)
                returns.extend(total.tolist())
    finally:
        env.close()
    return np.asarray(returns[:episodes])
