"""The batched suite environment: torchrl specs, rewards summed over the action repeat, fixed-length
episodes, reproducible initial states, and rendering only the frames a clip can reach."""

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from mftcn_bench.core.errors import SpecError
from mftcn_bench.rl.observation import observed_env
from mftcn_bench.rl.observers import StateObserver
from mftcn_bench.rl.suite_env import SuiteConfig
from mftcn_bench.sim.rendering import RenderSettings

RENDER = RenderSettings(shadowsize=16, offsamples=0, shadows=False, reflection=False)
CONFIG = SuiteConfig("cartpole", "swingup", "fixed", 24, 32, episode_length=40, action_repeat=4, render=RENDER,
                     frame_every=1)


class CountingObserver:
    """Records the frames it was given (embedded: push; history only: observe) and returns the state."""

    def __init__(self):
        self.pushes = []

    def observe(self, frames, episode_start, state):
        self.pushes.append((None if frames is None else frames.shape, bool(episode_start.all()), "observe",
                            np.array(state)))

    def push(self, frames, episode_start, state):
        self.pushes.append((None if frames is None else frames.shape, bool(episode_start.all()), "push",
                            np.array(state)))
        return state.astype(np.float32)


def test_specs_and_fixed_length_episodes():
    env = observed_env(CONFIG, 3, seed=0, observer=StateObserver(), embedding_dim=5, observer_uses_pixels=False)
    check_env_specs(env)
    rollout = env.rollout(CONFIG.agent_steps, break_when_any_done=False)
    done = rollout.get(("next", "done")).squeeze(-1)
    assert rollout.batch_size == torch.Size([3, 10])
    assert not done[:, :-1].any() and done[:, -1].all()


def test_reward_is_the_sum_over_the_action_repeat_and_states_are_reproducible():
    from dm_control import suite

    env = observed_env(CONFIG, 2, seed=5, observer=StateObserver(), embedding_dim=5, observer_uses_pixels=False)
    td = env.reset()
    first_obs = td.get("observation").clone()
    physics = [e.physics.get_state().copy() for e in env.base_env._envs]
    action = torch.tensor([[0.5], [-0.25]])
    td.set("action", action)
    reward = env.step(td).get(("next", "reward")).squeeze(-1)
    for i in range(2):  # the same physics stepped by hand
        plain = suite.load("cartpole", "swingup")
        plain.reset()
        with plain.physics.reset_context():
            plain.physics.set_state(physics[i])
        expected = sum(plain.step(action[i].numpy().astype(np.float64)).reward for _ in range(CONFIG.action_repeat))
        assert abs(float(reward[i]) - expected) < 1e-5
    again = observed_env(CONFIG, 2, seed=5, observer=StateObserver(), embedding_dim=5, observer_uses_pixels=False)
    assert torch.equal(again.reset().get("observation"), first_obs)  # same seed, same initial states
    assert not torch.equal(again.reset().get("observation"), first_obs)  # the next episode differs


def test_renders_only_the_frames_a_clip_can_reach():
    observer = CountingObserver()
    env = observed_env(CONFIG, 2, seed=0, observer=observer, embedding_dim=4, observer_uses_pixels=True,
                        lookback=3)
    td = env.reset()
    td.set("action", torch.zeros(2, 1))
    env.step(td)
    # one frame at the reset, then the last min(lookback 3, repeat 4) = 3 sub-steps of the repeat
    assert [p[0] for p in observer.pushes] == [(2, 24, 32, 3)] * 4
    assert [p[1] for p in observer.pushes] == [True, False, False, False]
    # only the last frame of the repeat is embedded (the observation the policy reads)
    assert [p[2] for p in observer.pushes] == ["push", "observe", "observe", "push"]
    blind = CountingObserver()
    env = observed_env(CONFIG, 2, seed=0, observer=blind, embedding_dim=4, observer_uses_pixels=False, lookback=3)
    td = env.reset()
    td.set("action", torch.zeros(2, 1))
    env.step(td)
    assert [p[0] for p in blind.pushes] == [None, None]  # no rendering; one observation a step


def test_embedding_difference_is_the_change_since_the_previous_simulator_frame():
    from dataclasses import replace

    from mftcn_bench.encoders.baselines import state_embedding

    config = replace(CONFIG, embedding_difference=True)
    env = observed_env(config, 2, seed=3, observer=StateObserver(), embedding_dim=5, observer_uses_pixels=False)
    check_env_specs(env)
    from dm_control import suite

    td = env.reset()
    assert td.get("observation").shape == (2, 10) and torch.all(td.get("observation")[:, 5:] == 0)
    for _ in range(3):
        start = env.base_env._envs[0].physics.get_state().copy()
        td.set("action", torch.full((2, 1), 0.7))
        td = env.step(td)["next"]
        obs = td.get("observation").numpy()
        now = np.stack([np.concatenate([e.physics.data.qpos, e.physics.data.qvel]) for e in env.base_env._envs])
        assert np.allclose(obs[:, :5], state_embedding(now), atol=1e-5)
        plain = suite.load("cartpole", "swingup")  # the same physics, one step short of the repeat
        plain.reset()
        with plain.physics.reset_context():
            plain.physics.set_state(start)
        for _ in range(config.action_repeat - 1):
            plain.step(np.array([0.7]))
        earlier = np.concatenate([plain.physics.data.qpos, plain.physics.data.qvel])[None]
        assert np.allclose(obs[0, :5] - obs[0, 5:], state_embedding(earlier)[0], atol=1e-5)
    counting = CountingObserver()
    env = observed_env(config, 2, seed=0, observer=counting, embedding_dim=4, observer_uses_pixels=True, lookback=1)
    td = env.reset()
    td.set("action", torch.zeros(2, 1))
    env.step(td)
    # lookback 1 renders the last two frames of the repeat, and embeds both
    assert [p[2] for p in counting.pushes] == ["push", "push", "push"]


def test_the_stream_has_the_data_sets_frame_rate():
    """With frame_every = action_repeat (an agent-rate data set) the encoder sees one frame per agent step,
    the frame after the repeat; with frame_every 2 of 4, the last frames of each step two physics steps apart.
    Either way a clip's frames are exactly as far apart as in its training data."""
    from dataclasses import replace

    from dm_control import suite

    def cart_positions(every: int, lookback: int) -> tuple[list[float], list[str]]:
        observer = CountingObserver()
        env = observed_env(replace(CONFIG, frame_every=every), 1, seed=0, observer=observer, embedding_dim=4,
                            observer_uses_pixels=True, lookback=lookback)
        td = env.reset()
        start = env.base_env._envs[0].physics.get_state().copy()
        for _ in range(2):
            td.set("action", torch.full((1, 1), 0.5))
            td = env.step(td)["next"]
        return [float(p[3][0, 0]) for p in observer.pushes], [p[2] for p in observer.pushes], start

    def replay(start, steps: list[int]) -> list[float]:
        plain = suite.load("cartpole", "swingup")
        plain.reset()
        with plain.physics.reset_context():
            plain.physics.set_state(start)
        seen, done = [], 0
        for step in steps:
            for _ in range(step - done):
                plain.step(np.array([0.5]))
            done = step
            seen.append(float(plain.physics.data.qpos[0]))
        return seen

    agent, how, start = cart_positions(every=4, lookback=3)
    assert how == ["push", "push", "push"], "one frame per agent step, each embedded"
    assert np.allclose(agent, replay(start, [0, 4, 8]), atol=1e-9)
    half, how, start = cart_positions(every=2, lookback=3)
    assert how == ["push", "observe", "push", "observe", "push"], "two frames an agent step, both within reach"
    assert np.allclose(half, replay(start, [0, 2, 4, 6, 8]), atol=1e-9)
    with pytest.raises(SpecError,
                       match=r"action_repeat \(4\) must be a multiple of the data set's action_repeat \(3\)"):
        replace(CONFIG, frame_every=3)


def test_the_difference_on_an_agent_rate_stream_is_the_change_since_the_last_agent_step():
    from dataclasses import replace

    from mftcn_bench.encoders.baselines import state_embedding

    config = replace(CONFIG, embedding_difference=True, frame_every=CONFIG.action_repeat)
    env = observed_env(config, 2, seed=3, observer=StateObserver(), embedding_dim=5, observer_uses_pixels=False)
    td = env.reset()
    previous = td.get("observation").numpy()[:, :5]
    for _ in range(3):
        td.set("action", torch.full((2, 1), 0.7))
        td = env.step(td)["next"]
        obs = td.get("observation").numpy()
        now = np.stack([np.concatenate([e.physics.data.qpos, e.physics.data.qvel]) for e in env.base_env._envs])
        assert np.allclose(obs[:, :5], state_embedding(now), atol=1e-5)
        assert np.allclose(obs[:, 5:], obs[:, :5] - previous, atol=1e-5)
        previous = obs[:, :5]


class SumReadout:
    """Maps each observation row to (sum, first - last): a fixed readout with a width of its own."""

    out_features = 2

    def __call__(self, observation):
        return np.stack([observation.sum(1), observation[:, 0] - observation[:, -1]], axis=1)


def test_readout_maps_the_observation_before_the_policy_sees_it():
    from dataclasses import replace

    config = replace(CONFIG, embedding_difference=True)
    plain = observed_env(config, 2, seed=3, observer=StateObserver(), embedding_dim=5, observer_uses_pixels=False)
    mapped = observed_env(config, 2, seed=3, observer=StateObserver(), embedding_dim=5, observer_uses_pixels=False,
                           readout=SumReadout())
    assert mapped.observation_spec["observation"].shape == (2, 2)
    check_env_specs(observed_env(config, 2, seed=3, observer=StateObserver(), embedding_dim=5,
                                  observer_uses_pixels=False, readout=SumReadout()))
    td_plain, td_mapped = plain.reset(), mapped.reset()
    for _ in range(3):  # the same physics: the readout of the plain observation ([e_t, e_t - e_t-1]) each step
        assert np.allclose(td_mapped.get("observation").numpy(), SumReadout()(td_plain.get("observation").numpy()),
                           atol=1e-5)
        td_plain.set("action", torch.full((2, 1), -0.4))
        td_mapped.set("action", torch.full((2, 1), -0.4))
        td_plain, td_mapped = plain.step(td_plain)["next"], mapped.step(td_mapped)["next"]
        assert td_mapped.get("observation").dtype == torch.float32
    assert np.allclose(td_mapped.get("observation").numpy(), SumReadout()(td_plain.get("observation").numpy()),
                       atol=1e-5)
