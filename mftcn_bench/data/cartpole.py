"""Multi-view cartpole videos under random actions from random initial states.

Each episode starts from a random state (cart position, pole angle and both velocities drawn from the
ranges in the spec) and applies random actions: with probability `action_keep_prob` the previous action
is kept, otherwise a new one is drawn uniformly from [-1, 1] (a persistent random walk like PVE's
exploration). Every frame is rendered from all cameras after the state is set, and the true state
(x, theta, x_dot, theta_dot) and the action taken are recorded with it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from mftcn_bench.sim.rendering import MultiViewRenderer, RenderSettings, ensure_gl


def camera_names() -> list[str]:
    """The cameras the suite's cartpole model defines (read from its XML, no rendering)."""
    ensure_gl()  # dm_control picks its GL backend on import
    import mujoco
    from dm_control.suite import cartpole

    xml, assets = cartpole.get_model_and_assets()
    model = mujoco.MjModel.from_xml_string(xml, assets)
    return [model.camera(i).name for i in range(model.ncam)]


def collect_episode(config: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
    """Episode `index` of the dataset `config`; a pure function of (config, index)."""
    ensure_gl()
    from dm_control import suite

    rng = np.random.default_rng([int(config["seed"]), index])
    env = suite.load("cartpole", "swingup", task_kwargs={"random": int(rng.integers(2**31))})
    physics = env.physics
    renderer = MultiViewRenderer(physics, config["cameras"], int(config["height"]), int(config["width"]),
                                 RenderSettings.from_table(f"dataset {config['name']!r}", config["render"]))
    init = config["init"]
    env.reset()
    with physics.reset_context():
        physics.named.data.qpos["slider"] = rng.uniform(-init["x_range"], init["x_range"])
        physics.named.data.qpos["hinge_1"] = rng.uniform(-np.pi, np.pi)
        physics.named.data.qvel["slider"] = rng.normal(0.0, init["x_dot_std"])
        physics.named.data.qvel["hinge_1"] = rng.normal(0.0, init["theta_dot_std"])

    length = int(config["episode_length"])
    keep_prob = float(config["action_keep_prob"])
    frames = np.empty((len(config["cameras"]), length) + (int(config["height"]), int(config["width"]), 3),
                      dtype=np.uint8)
    state = np.empty((length, 4), dtype=np.float64)
    action = np.empty((length, 1), dtype=np.float32)
    current = rng.uniform(-1.0, 1.0)
    for t in range(length):
        frames[:, t] = renderer.render()
        state[t] = np.concatenate([physics.data.qpos, physics.data.qvel])
        if rng.random() >= keep_prob:
            current = rng.uniform(-1.0, 1.0)
        action[t] = current
        for _ in range(int(config["action_repeat"])):
            env.step(action[t])
    return {"frames": frames, "state": state, "action": action}


# The state a cartpole probe or policy is asked for: the pole's angle as sin and cos (a spinning pole's
# angle is unbounded), in this order. Shared by the probe task, the state encoders and the paper tables.
TARGETS = ("x_cart", "sin_theta", "cos_theta", "x_dot", "theta_dot")


def state_targets(state: np.ndarray) -> np.ndarray:
    """Simulator state [T, 4] (x, theta, x_dot, theta_dot) -> targets [T, 5] in TARGETS order."""
    x, theta, x_dot, theta_dot = state.T
    return np.stack([x, np.sin(theta), np.cos(theta), x_dot, theta_dot], axis=1)
