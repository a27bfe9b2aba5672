"""Demonstration videos (`rl/demos.py`): the frames, states and actions of a policy's episodes, filmed at
the data set's rate."""

from __future__ import annotations

import numpy as np

from mftcn_bench.core import registry
from mftcn_bench.core.specs import resolve_config
from mftcn_bench.rl.demos import ExpertDemoCollector
from mftcn_bench.rl.suite_env import physics_state
from mftcn_bench.sim.rendering import ensure_gl
from mftcn_bench.tasks.control import ExpertDemoControlTask


class Alternating:
    """A stand-in expert: a different action at each decision, so a frame records which decision it saw."""

    def __init__(self, dim: int) -> None:
        self.dim, self.decisions = dim, 0

    def act(self, state: np.ndarray) -> np.ndarray:
        self.decisions += 1
        return np.full(self.dim, 0.5 if self.decisions % 2 else -0.5)


def test_demonstrations_film_a_frame_every_action_repeat_steps_with_the_state_and_action_of_that_step():
    _, config = resolve_config(registry.get("encoders", "true-state").spec, registry.get("tasks", "cheetah").spec,
                               "smoke", [("task.dataset.episode_length", 6), ("task.dataset.height", 16),
                                         ("task.dataset.width", 16)])
    task = ExpertDemoControlTask(config["task"], 0)
    data = dict(task.dataset_config)
    every, repeat = int(data["action_repeat"]), task.env_config.action_repeat
    assert every == repeat == 4 and task.data_frame_every() == 4  # the agent rate
    expert = Alternating(6)
    episode = ExpertDemoCollector(None, task.env_config, task.expert.ppo, policy=expert)(data, 3)
    assert episode["frames"].shape == (2, 6, 16, 16, 3) and expert.decisions == 6

    # The same episode stepped here: the recorded states are every 4th physics step's, before its action.
    ensure_gl()
    from dm_control import suite

    rng = np.random.default_rng([int(data["seed"]), 3])
    env = suite.load("cheetah", "run", task_kwargs={"random": int(rng.integers(2**31))})
    env.reset()
    replay = Alternating(6)
    for t in range(6):
        np.testing.assert_allclose(episode["state"][t], physics_state(env.physics, "cheetah"))
        action = replay.act(episode["state"][t])
        np.testing.assert_array_equal(episode["action"][t], action)
        for _ in range(every):
            env.step(action)
