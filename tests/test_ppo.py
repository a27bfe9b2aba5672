"""PPO on the batched environment: reproducible from the seed, and a killed run resumes exactly."""

import numpy as np
import pytest
import torch

from mftcn_bench.rl.checkpoint_progress import CheckpointProgress, checkpoint_progress
from mftcn_bench.rl.expert import ExpertPolicy, ensure_expert, state_env_factory
from mftcn_bench.rl.ppo import PPOConfig, evaluate_policy, train_ppo
from mftcn_bench.rl.suite_env import SuiteConfig
from mftcn_bench.sim.rendering import RenderSettings

RENDER = RenderSettings(shadowsize=16, offsamples=0, shadows=False, reflection=False)
ENV = SuiteConfig("cartpole", "swingup", "fixed", 24, 32, episode_length=40, action_repeat=4, render=RENDER,
                     frame_every=1)
PPO = PPOConfig(frames=480, num_envs=2, episodes_per_batch=1, epochs=2, minibatch_size=8, lr=3e-4, anneal_lr=True,
                gamma=0.99, lmbda=0.95, clip_epsilon=0.2, clip_value=0.2, entropy_coeff=0.01, critic_coeff=0.5,
                max_grad_norm=0.5, reward_scale=0.1, hidden=[16, 16], eval_episodes=3, checkpoint_every=1)


class Stop(Exception):
    pass


def _train(workdir, stop_after=None):
    def progress(batch, total, stats):
        if batch == stop_after:
            raise Stop
    return train_ppo(state_env_factory(ENV), PPO, 3, workdir, progress)


def _params(nets):
    return torch.cat([p.detach().flatten() for p in nets.parameters()])


def test_same_seed_same_policy_and_curve(tmp_path):
    nets_a, state_a = _train(tmp_path / "a")
    nets_b, state_b = _train(tmp_path / "b")
    assert state_a.batch == 6 and state_a.frames == 480  # 6 batches of 2 envs x 10 steps x 4 repeats
    assert state_a.curve_return == state_b.curve_return
    assert torch.equal(_params(nets_a), _params(nets_b))


def test_each_batch_records_cleanrls_diagnostics(tmp_path):
    """approx KL, clip fraction, explained variance and entropy, one value per batch, in their ranges; the
    clip fraction is the share of steps whose ratio left [1 - eps, 1 + eps], so it is 0 in the first
    minibatch and cannot exceed 1."""
    _, state = _train(tmp_path)
    assert sorted(state.diagnostics) == ["approx_kl", "clip_fraction", "entropy", "explained_variance"]
    for name, column in state.diagnostics.items():
        assert len(column) == state.batch == 6, name
        assert all(np.isfinite(column)), name
    assert all(0.0 <= c <= 1.0 for c in state.diagnostics["clip_fraction"])
    assert all(e <= 1.0 for e in state.diagnostics["explained_variance"])
    assert all(abs(kl) < 1.0 for kl in state.diagnostics["approx_kl"])


def test_killed_run_resumes_from_its_checkpoint_to_the_same_result(tmp_path):
    nets_a, state_a = _train(tmp_path / "a")
    with pytest.raises(Stop):
        _train(tmp_path / "b", stop_after=3)
    assert (tmp_path / "b" / "ppo_checkpoint.pt").exists()
    # what `sweep status` reads of it: 3 batches of 80 frames, the third batch's training return
    assert checkpoint_progress(tmp_path / "b") == CheckpointProgress(240, state_a.curve_return[2])
    nets_b, state_b = _train(tmp_path / "b")
    assert state_b.curve_return == state_a.curve_return and state_b.batch == 6
    assert state_b.diagnostics == state_a.diagnostics  # the checkpoint carries the diagnostics' curves
    assert torch.equal(_params(nets_a), _params(nets_b))
    make_env = state_env_factory(ENV)
    returns_a = evaluate_policy(make_env, nets_a, 3, 2, seed=3)
    assert len(returns_a) == 3
    assert returns_a.tolist() == evaluate_policy(make_env, nets_b, 3, 2, seed=3).tolist()


def test_truncated_checkpoint_is_refused_with_one_line(tmp_path):
    from mftcn_bench.core.errors import TrainingError

    with pytest.raises(Stop):
        _train(tmp_path, stop_after=1)
    path = tmp_path / "ppo_checkpoint.pt"
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(TrainingError, match="cannot be read"):
        _train(tmp_path)
    assert checkpoint_progress(tmp_path) is None and checkpoint_progress(tmp_path / "none") is None


def test_expert_is_trained_once_and_acts_like_the_trained_policy(tmp_path):
    import json

    from tensordict import TensorDict
    from torchrl.envs import ExplorationType, set_exploration_type

    from mftcn_bench.rl.observers import StateObserver

    path = ensure_expert(tmp_path, ENV, PPO, seed=1)
    stamp = path.stat().st_mtime_ns
    assert ensure_expert(tmp_path, ENV, PPO, seed=1) == path and path.stat().st_mtime_ns == stamp
    expert = ExpertPolicy(path, ENV, PPO)
    action = expert.act([0.1, 0.2, 0.0, -0.3])
    assert expert.act([0.1, 0.2, 0.0, -0.3]).tolist() == action.tolist()
    # The mean action: tanh of the policy head's loc for this state, computed here from the expert's own
    # networks. A draw from the TanhNormal would be off by about its scale (near 1 after so little training).
    observation = torch.from_numpy(StateObserver().push(None, np.ones(1, bool), np.array([[0.1, 0.2, 0.0, -0.3]])))
    with torch.no_grad():
        head = expert._nets.policy(TensorDict({"observation": observation}, batch_size=[1]))
    assert action.shape == (1,)
    assert np.allclose(action, torch.tanh(head.get("loc"))[0].double().numpy(), atol=1e-6)
    # The same networks as PPO trains from this seed (training is deterministic), acting by their mean:
    nets, _ = train_ppo(state_env_factory(ENV), PPO, 1, tmp_path / "again", lambda *a: None)
    states = np.array([[0.1, 0.2, 0.0, -0.3], [-0.5, 3.0, 1.0, 2.0]])
    obs = torch.from_numpy(StateObserver().push(None, np.ones(2, bool), states))
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        want = nets.policy(TensorDict({"observation": obs}, batch_size=[2])).get("action").double().numpy()
    got = np.stack([expert.act(s) for s in states])
    assert np.allclose(got, want, atol=1e-6) and not np.allclose(got[0], got[1])
    summary = json.loads((path.parent / "expert.json").read_text())
    returns = evaluate_policy(state_env_factory(ENV), nets, PPO.eval_episodes, 2, 1)
    assert summary["return_mean"] == pytest.approx(float(returns.mean()))


def test_the_policy_acts_by_tanh_of_its_loc_and_scores_its_draws_by_the_tanh_normal_density():
    """What the test episodes and PPO's importance ratios rest on: the deterministic action is tanh(loc)
    (not loc, nor loc clipped to [-1, 1]), and the log-probability stored with a drawn action a is the
    change-of-variables density of the TanhNormal, log N(atanh a; loc, scale) - log(1 - a^2), summed over the
    action's dimensions (a Normal's density without the Jacobian term would give other ratios)."""
    from dataclasses import replace

    from tensordict import TensorDict
    from torchrl.envs import ExplorationType, set_exploration_type

    from mftcn_bench.rl.observation import observed_env
    from mftcn_bench.rl.observers import StateObserver
    from mftcn_bench.rl.ppo import PolicyNetworks

    torch.manual_seed(0)
    env = observed_env(ENV, 2, 0, StateObserver(), 5, False)
    # Full-size last-layer weights: locs of order 1, where tanh(loc), loc and clip(loc) tell apart.
    nets = PolicyNetworks(env, replace(PPO, policy_init_scale=1.0), None)
    env.close()
    observations = TensorDict({"observation": 3 * torch.randn(256, 5)}, batch_size=[256])
    with torch.no_grad():
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            mean = nets.policy(observations.clone())
        with set_exploration_type(ExplorationType.RANDOM):
            drawn = nets.policy(observations.clone())
    loc, scale = mean.get("loc").double(), mean.get("scale").double()
    assert loc.abs().max() > 0.5, "locs too small for tanh(loc) and loc to differ"
    assert torch.allclose(mean.get("action").double(), torch.tanh(loc), atol=1e-6)
    action = drawn.get("action").double()
    # Away from saturation, where atanh of a float32 action recovers the drawn pre-tanh value.
    kept = (action.abs() < 0.999).all(-1)
    assert kept.float().mean() > 0.9
    by_hand = (torch.distributions.Normal(loc, scale).log_prob(torch.atanh(action)) - torch.log1p(-action**2)).sum(-1)
    assert torch.allclose(drawn.get("action_log_prob").double()[kept], by_hand[kept], atol=1e-3)


def test_running_normalizer_matches_numpy_over_all_batches():
    import numpy as np

    from mftcn_bench.rl.ppo import RunningNormalizer

    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, size=(n, 3)) for n in (5, 17, 8)]
    norm = RunningNormalizer(3)
    for b in batches:
        norm.update(torch.from_numpy(b).float())
    every = np.concatenate(batches).astype(np.float32).astype(np.float64)
    assert np.allclose(norm.mean.numpy(), every.mean(0)) and np.allclose(norm.var.numpy(), every.var(0))
    x = torch.tensor([[3.0, 3.0, 1e6]])
    expected = (x.double() - every.mean(0)) / np.sqrt(every.var(0) + 1e-8)
    assert torch.allclose(norm(x).double()[0, :2], expected[0, :2], atol=1e-5) and norm(x)[0, 2] == 10.0


def test_pixel_critic_sees_one_environment_at_a_time_when_computing_advantages(tmp_path):
    """GAE's value calls are chunked by environment for a pixel trunk: a whole batch of clips at once needs
    tens of GB of CNN activations at 160x160."""
    from torch import nn

    from mftcn_bench.rl.observation import PixelClip, observed_env

    no_grad_batches: list[int] = []
    grad_batches: list[int] = []

    class Trunk(nn.Module):
        out_features = 4

        def __init__(self) -> None:
            super().__init__()
            self.linear = nn.Linear(3 * ENV.height * ENV.width, 4)

        def forward(self, clips: torch.Tensor) -> torch.Tensor:
            flat = clips.reshape(-1, 3 * ENV.height * ENV.width).float() / 255.0
            (grad_batches if torch.is_grad_enabled() else no_grad_batches).append(flat.shape[0])
            return self.linear(flat).reshape(*clips.shape[:-4], 4)

    def make_env(num_envs: int, seed: int):
        return observed_env(ENV, num_envs, seed, None, 4, True, pixel_clip=PixelClip(1, 1))

    config = PPOConfig(**{**PPO.__dict__, "frames": 160, "num_envs": 3})
    trunk = Trunk()
    before = trunk.linear.weight.detach().clone()
    nets, _ = train_ppo(make_env, config, 0, tmp_path, lambda *args: None, trunk=trunk)
    agent_steps = ENV.episode_length // ENV.action_repeat
    # Collection steps the policy on all 3 environments at once (3 clips); advantages: one environment's
    # 10 steps per call, never the batch's 30 (or 60 with the next observations).
    assert max(no_grad_batches) == agent_steps
    assert no_grad_batches.count(agent_steps) == 2 * 3 * 2  # 2 batches x 3 environments x (obs, next obs)
    # The update runs the trunk once per minibatch for both heads (30 steps in minibatches of 8: 8, 8, 8, 6;
    # 2 epochs, 2 batches), not once per head, and the optimiser moves it.
    assert grad_batches == [8, 8, 8, 6] * 2 * 2
    assert not torch.equal(trunk.linear.weight, before)
    assert {id(p) for p in nets.trainable()} >= {id(p) for p in trunk.parameters()}


def test_the_update_sees_the_normalisation_the_batch_was_collected_with(tmp_path, monkeypatch):
    """Before any gradient step of a batch, the policy gives the batch's actions the log-probabilities
    stored when it was collected (importance ratio 1): the observation statistics have not moved."""
    import mftcn_bench.rl.ppo as ppo

    update, ratios = ppo._update, []

    def checked(batch, common, loss, advantage, optimizer, config):
        with torch.no_grad():
            dist = loss.actor_network.get_dist(common(batch.clone()))
            stored = batch.get("action_log_prob")
            ratios.append(float((dist.log_prob(batch.get("action")) - stored).abs().max()))
        return update(batch, common, loss, advantage, optimizer, config)

    monkeypatch.setattr(ppo, "_update", checked)
    _train(tmp_path)
    assert len(ratios) == 6 and max(ratios) < 1e-4, ratios


def test_one_update_on_a_fixed_batch_against_hand_computed_steps():
    """`_update`: advantages once per batch on scaled rewards (the caller's batch untouched), `epochs` passes
    of shuffled minibatches covering every step, the summed losses' gradient clipped to `max_grad_norm`, and
    the statistics averaged over minibatches."""
    import math
    from dataclasses import replace

    from tensordict import TensorDict
    from torch import nn

    from mftcn_bench.rl.ppo import _update

    batch = TensorDict({"observation": torch.randn(2, 5, 3), ("next", "reward"): torch.ones(2, 5, 1)},
                       batch_size=[2, 5])
    seen_rewards = []

    def advantage(td):
        seen_rewards.append(td.get(("next", "reward")).clone())
        td.set("advantage", torch.zeros(*td.shape, 1))

    class FixedLoss(nn.Module):
        """loss_objective = 100 * sum(p) (gradient 100 per coordinate), loss_critic = 1, entropy = 0.5."""

        def __init__(self):
            super().__init__()
            self.p = nn.Parameter(torch.zeros(3))
            self.sizes = []

        def forward(self, td):
            self.sizes.append(td.shape[0])
            assert "advantage" in td.keys()
            one, k = torch.ones(()), len(self.sizes)
            # the diagnostics torchrl's ClipPPOLoss reports, different in each minibatch k = 1..6
            return TensorDict({"loss_objective": 100 * self.p.sum(), "loss_critic": one, "entropy": one / 2,
                               "kl_approx": one * k / 100, "clip_fraction": one * k / 10,
                               "explained_variance": torch.full((1,), 1.0 - k / 10)}, [])

    loss = FixedLoss()
    config = replace(PPO, epochs=2, minibatch_size=4, max_grad_norm=0.5, reward_scale=0.1)
    stats = _update(batch, lambda td: td, loss, advantage, torch.optim.SGD(loss.parameters(), lr=1.0), config)
    assert len(seen_rewards) == 1 and torch.allclose(seen_rewards[0], torch.full((2, 5, 1), 0.1))
    assert torch.equal(batch.get(("next", "reward")), torch.ones(2, 5, 1)), "the caller's batch is not scaled"
    assert loss.sizes == [4, 4, 2, 4, 4, 2]  # 10 steps in minibatches of 4, twice
    # Each step moves p by lr * 0.5 along -(1, 1, 1) / sqrt(3): the clipped gradient, 6 times.
    assert torch.allclose(loss.p.detach(), torch.full((3,), -6 * 0.5 / math.sqrt(3)), atol=1e-6)
    assert stats["loss_critic"] == 1.0 and stats["entropy"] == 0.5
    # means over the 6 minibatches: (1 + ... + 6) / 6 = 3.5
    assert math.isclose(stats["kl_approx"], 0.035, rel_tol=1e-6)
    assert math.isclose(stats["clip_fraction"], 0.35, rel_tol=1e-6)
    assert math.isclose(stats["explained_variance"], 0.65, rel_tol=1e-6)
    expected_objective = sum(100 * 3 * (-k * 0.5 / math.sqrt(3)) for k in range(6)) / 6
    assert math.isclose(stats["loss_objective"], expected_objective, rel_tol=1e-5)


@pytest.mark.slow
def test_ppo_raises_the_return_of_a_small_task(tmp_path):
    """Cartpole balance from state, 16,000 frames: the training return of the last batches is well above
    the first ones (seed 0 gives 101, 91 -> 120, 117, 119); with lr 0 nothing is learnt."""
    from dataclasses import replace

    env = SuiteConfig("cartpole", "balance", "fixed", 24, 32, episode_length=200, action_repeat=4, render=RENDER,
                     frame_every=1)
    config = replace(PPO, frames=16000, num_envs=8, epochs=4, minibatch_size=64, lr=3e-3, gamma=0.97,
                     entropy_coeff=0.0, hidden=[32, 32], checkpoint_every=100)

    def rise(ppo, workdir):
        _, state = train_ppo(state_env_factory(env), ppo, 0, workdir, lambda *a: None)
        curve = state.curve_return
        return sum(curve[-3:]) / 3 - sum(curve[:2]) / 2

    assert rise(config, tmp_path / "learns") > 10.0
    assert abs(rise(replace(config, lr=0.0), tmp_path / "frozen")) < 10.0


def test_the_objectives_are_the_specs_and_gae_bootstraps_at_the_time_limit_only():
    """ppo_objectives holds the spec's settings, and on an episode the environment ends by its time limit
    (truncated, not terminated) GAE's target at the last step is r + gamma V(s'): the critic's value of the
    state after the limit, which a terminated episode would not have."""
    from mftcn_bench.rl.observation import observed_env
    from mftcn_bench.rl.observers import StateObserver
    from mftcn_bench.rl.ppo import PolicyNetworks, ppo_objectives

    env = observed_env(ENV, 2, 0, StateObserver(), 5, False)
    nets = PolicyNetworks(env, PPO, None)
    loss, gae = ppo_objectives(nets, PPO)
    settings = [float(x) for x in (loss.clip_epsilon, loss.entropy_coeff, loss.critic_coeff, loss.clip_value,
                                   gae.gamma, gae.lmbda)]
    assert settings == pytest.approx([PPO.clip_epsilon, PPO.entropy_coeff, PPO.critic_coeff, PPO.clip_value,
                                      PPO.gamma, PPO.lmbda], rel=1e-6)
    assert loss.normalize_advantage and loss.loss_critic_type == "l2" and not gae.average_gae

    with torch.no_grad():
        rollout = env.rollout(ENV.agent_steps, nets.policy, break_when_any_done=False)
    last = rollout[:, -1]
    assert bool(last.get(("next", "truncated")).all()) and not bool(rollout.get(("next", "terminated")).any())
    with torch.no_grad():
        gae(rollout)
        v_next = nets.value(last.get("next").clone()).get("state_value")
    expected = last.get(("next", "reward")) + PPO.gamma * v_next
    assert torch.allclose(rollout[:, -1].get("value_target"), expected, atol=1e-5), "bootstrapped at truncation"
    terminated = rollout.clone()
    terminated.set(("next", "terminated"), terminated.get(("next", "truncated")).clone())
    with torch.no_grad():
        gae(terminated)
    assert torch.allclose(terminated[:, -1].get("value_target"), last.get(("next", "reward")), atol=1e-5)


def test_a_task_that_terminates_is_refused_in_one_line():
    from mftcn_bench.core.errors import TrainingError
    from mftcn_bench.rl.observation import observed_env
    from mftcn_bench.rl.observers import StateObserver
    from mftcn_bench.rl.suite_env import suite_env_of

    env = observed_env(ENV, 1, 0, StateObserver(), 5, False)
    td = env.reset()
    task = suite_env_of(env)._envs[0].task
    task.get_termination = lambda physics: 0.0  # as a suite task whose episode ended early
    td.set("action", torch.zeros(1, 1))
    with pytest.raises(TrainingError, match="ended an episode early .* tasks that never terminate"):
        env.step(td)


def test_evaluation_starts_every_test_episode_from_its_own_initial_state(tmp_path):
    """evaluate_policy's episodes (over several rollouts of a batch of environments) all start from distinct
    initial states, and from other ones than training's (its environments are seeded apart)."""
    from mftcn_bench.rl.observation import observed_env
    from mftcn_bench.rl.observers import StateObserver
    from mftcn_bench.rl.ppo import PolicyNetworks

    starts: list[tuple[float, ...]] = []

    class Recording(StateObserver):
        def push(self, frames, episode_start, state):
            if episode_start.all():
                starts.extend(tuple(row) for row in np.round(state, 12))
            return super().push(frames, episode_start, state)

    def make_env(num_envs: int, seed: int):
        return observed_env(ENV, num_envs, seed, Recording(), 5, False)

    nets = PolicyNetworks(make_env(2, 0), PPO, None)
    starts.clear()
    returns = evaluate_policy(make_env, nets, episodes=6, num_envs=2, seed=0)
    assert len(returns) == 6 and len(starts) == 6
    assert len(set(starts)) == 6, "every test episode from its own initial state"
    evaluated = set(starts)
    starts.clear()
    make_env(2, 0).reset()  # training's first episodes, the same run seed
    assert len(starts) == 2 and not set(starts) & evaluated


def test_the_collector_acts_with_the_weights_of_each_update(tmp_path, monkeypatch):
    """After every batch's update the collector's policy is refreshed (a copy on another device would
    otherwise collect with the first weights): at the end its parameters are the trained ones."""
    from torchrl.collectors import Collector

    refreshed: list[bool] = []
    update = Collector.update_policy_weights_

    def recording(self, *args, **kwargs):
        update(self, *args, **kwargs)
        trained = dict(self._trained.named_parameters())
        refreshed.append(all(torch.equal(p, trained[n]) for n, p in self.policy.named_parameters()))

    monkeypatch.setattr(Collector, "update_policy_weights_", recording)
    init = Collector.__init__

    def keeping(self, env, policy, *args, **kwargs):
        init(self, env, policy, *args, **kwargs)
        self._trained = policy

    monkeypatch.setattr(Collector, "__init__", keeping)
    train_ppo(state_env_factory(ENV), PPO, 0, tmp_path, lambda *args: None)
    assert refreshed == [True] * 6, "one refresh per batch (480 frames: 6 batches of 2 envs x 10 steps x 4)"


def test_evaluation_closes_its_environments(monkeypatch):
    """Test episodes run on environments of their own, closed after (each rendering one holds an EGL context)."""
    from mftcn_bench.rl.observation import observed_env
    from mftcn_bench.rl.observers import StateObserver
    from mftcn_bench.rl.ppo import PolicyNetworks
    from mftcn_bench.rl.suite_env import SuiteBatchEnv

    closed: list[int] = []
    close = SuiteBatchEnv.close

    def counting(self, **kwargs):
        closed.append(self.num_envs)
        close(self, **kwargs)

    monkeypatch.setattr(SuiteBatchEnv, "close", counting)

    def make_env(num_envs: int, seed: int):
        return observed_env(ENV, num_envs, seed, StateObserver(), 5, False)

    nets = PolicyNetworks(make_env(2, 0), PPO, None)
    evaluate_policy(make_env, nets, episodes=2, num_envs=3, seed=0)
    assert closed == [3]


def test_the_pixel_update_computes_what_each_head_running_the_trunk_computes():
    """The harness's update (trunk once per minibatch for both heads, channels-last weights) moves every
    weight as torchrl's ClipPPOLoss does when given the whole actor and critic operators (each head running
    its own pass of the trunk, default layout): the speed-up changes no number beyond float rounding."""
    import copy
    from dataclasses import replace

    from torch import nn
    from torchrl.collectors import Collector
    from torchrl.objectives import ClipPPOLoss

    from mftcn_bench.encoders.baselines import PixelsCNNNet
    from mftcn_bench.encoders.frame_cnn import CNNConfig
    from mftcn_bench.rl.observation import PixelClip, observed_env
    from mftcn_bench.rl.ppo import PolicyNetworks, _update, ppo_objectives
    from mftcn_bench.tasks.control import ClipTrunk

    config = replace(PPO, num_envs=2, epochs=2, minibatch_size=8)
    env = observed_env(ENV, 2, 0, None, 8, True, pixel_clip=PixelClip(1, 1))
    torch.manual_seed(0)
    net = PixelsCNNNet(CNNConfig(channels=[8, 8], kernels=[5, 3], strides=[2, 2]), 1, 8)
    reference_net = copy.deepcopy(net)
    torch.manual_seed(1)
    nets = PolicyNetworks(env, config, ClipTrunk(net, 8))
    torch.manual_seed(1)
    reference = PolicyNetworks(env, config, ClipTrunk(reference_net, 8))
    assert next(nets.common.parameters()).is_contiguous(memory_format=torch.channels_last)
    initial = torch.cat([p.detach().flatten() for p in nets.trainable()])
    assert torch.equal(initial, torch.cat([p.detach().flatten() for p in reference.trainable()]))
    collector = Collector(env, nets.policy, frames_per_batch=20, total_frames=20, reset_at_each_iter=True,
                          auto_register_policy_transforms=False)
    batch = next(iter(collector))
    collector.shutdown()

    loss, advantage = ppo_objectives(nets, config, pixels=True)
    reference_loss = ClipPPOLoss(reference.policy, reference.value, clip_epsilon=config.clip_epsilon,
                                 clip_value=config.clip_value, entropy_coeff=config.entropy_coeff,
                                 critic_coeff=config.critic_coeff, loss_critic_type="l2", normalize_advantage=True)
    torch.manual_seed(2)
    stats = _update(batch, nets.common, loss, advantage, torch.optim.Adam(nets.trainable(), lr=1e-3), config)
    torch.manual_seed(2)
    reference_stats = _update(batch, nn.Identity(), reference_loss, ppo_objectives(reference, config, pixels=True)[1],
                              torch.optim.Adam(reference_loss.parameters(), lr=1e-3), config)
    moved = torch.cat([p.detach().flatten() for p in nets.trainable()])
    expected = torch.cat([p.detach().flatten() for p in reference.trainable()])
    assert (moved - initial).abs().max() > 1e-4, "the update moved the weights"
    assert torch.allclose(moved, expected, atol=1e-5), float((moved - expected).abs().max())
    assert stats.keys() == reference_stats.keys()
    assert all(abs(stats[k] - reference_stats[k]) < 1e-4 for k in stats)
