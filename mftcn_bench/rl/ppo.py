"""PPO on a frozen embedding with torchrl: ClipPPOLoss, GAE and a Collector over `SuiteBatchEnv` (transformed).

One training batch is `episodes_per_batch` whole episodes of every environment: the collector resets
the batch at the start of each one and each environment's initial state comes from (seed, instance,
episode number), so the data of batch k is a pure function of the seed and the networks at batch k. A
killed run resumes from its last checkpoint (networks, optimiser, observation statistics, RNG, curves)
and continues exactly where the checkpoint left it.

What made PPO learn swing-up from state reliably here (measured, see the task spec): action repeat,
many environments stepped in one process, running observation normalisation (statistics updated after
each batch's update and saved with the networks), reward scaling, a small
initial policy output, gradient-norm clipping, value clipping and a linearly annealed learning rate. The
policy's only input is the observation: the encoder's embedding (or, for pixels-cnn, the raw clip through
a CNN trained by the PPO losses of both heads).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from tensordict.nn.distributions.continuous import AddStateIndependentNormalScale
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type
from torchrl.modules import MLP, ActorValueOperator, IndependentNormal, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from mftcn_bench.core.device import cuda_rng_state, restore_cuda_rng_state
from mftcn_bench.core.errors import SpecError, TrainingError
from mftcn_bench.core.fileio import atomic_write_bytes
from mftcn_bench.core.progress import Progress
from mftcn_bench.rl.suite_env import EnvFactory, suite_env_of

DISTRIBUTIONS = {"tanh_normal": TanhNormal, "normal": IndependentNormal}


@dataclass(frozen=True)
class PPOConfig:
    """The `[ppo]` table of a control task's spec."""

    frames: int                       # env (physics) frames of training, action repeat included
    num_envs: int
    episodes_per_batch: int           # whole episodes of every environment in one batch
    epochs: int
    minibatch_size: int
    lr: float
    anneal_lr: bool
    gamma: float
    lmbda: float
    clip_epsilon: float
    clip_value: float
    entropy_coeff: float
    critic_coeff: float
    max_grad_norm: float
    reward_scale: float
    hidden: list[int] = field(default_factory=lambda: [256, 256])
    policy_init_scale: float = 0.01   # last policy layer's weights scaled down: actions start near 0
    distribution: str = "tanh_normal"  # or "normal" (actions clipped to [-1, 1] by the environment)
    state_independent_std: bool = False  # a learned log-std per action dimension instead of a network output
    normalize_observations: bool = True
    eval_episodes: int = 100
    checkpoint_every: int = 10        # batches


# Per-batch diagnostics: name -> the ClipPPOLoss output averaged over the batch's minibatches.
DIAGNOSTICS: dict[str, str] = {"approx_kl": "kl_approx", "clip_fraction": "clip_fraction",
                               "explained_variance": "explained_variance", "entropy": "entropy"}


@dataclass
class TrainState:
    batch: int = 0
    frames: int = 0
    wall_s: float = 0.0
    curve_frames: list[float] = field(default_factory=list)
    curve_wall_s: list[float] = field(default_factory=list)
    curve_return: list[float] = field(default_factory=list)
    # cleanrl's per-batch diagnostics (`DIAGNOSTICS`): a policy stuck in an optimum keeps a low KL and clip
    # fraction with a critic that explains its returns; one that lacks information has a critic that cannot.
    diagnostics: dict[str, list[float]] = field(default_factory=dict)



class RunningNormalizer(nn.Module):
    """(x - mean) / std with statistics of every observation collected so far, updated once per batch
    after its PPO update (so a batch is collected and learned from with the same statistics) and saved
    with the networks."""

    def __init__(self, size: int, clip: float = 10.0, eps: float = 1e-8) -> None:
        super().__init__()
        self.clip, self.eps = clip, eps
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("var", torch.ones(size, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merge the statistics of `x` [..., size] (parallel-variance formula)."""
        x = x.reshape(-1, x.shape[-1]).double()
        n, mean, var = x.shape[0], x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        self.var.copy_((self.var * self.count + var * n + delta**2 * self.count * n / total) / total)
        self.mean.add_(delta * n / total)
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.count == 0:
            return x
        z = (x - self.mean.to(x.dtype)) / torch.sqrt(self.var.to(x.dtype) + self.eps)
        return z.clamp(-self.clip, self.clip)


class PolicyNetworks(nn.Module):
    """Actor and critic (with a shared trunk for pixel input); built from the environment's specs."""

    def __init__(self, env: EnvBase, config: PPOConfig, trunk: nn.Module | None) -> None:
        super().__init__()
        action_dim = env.action_spec.shape[-1]
        in_key = "observation" if trunk is None else "pixels"
        self.normalizer: RunningNormalizer | None = None
        if trunk is None:
            features = env.observation_spec["observation"].shape[-1]
            if config.normalize_observations:
                self.normalizer = RunningNormalizer(features)
            common = TensorDictModule(self.normalizer or nn.Identity(), in_keys=[in_key], out_keys=["features"])
        else:
            common = TensorDictModule(trunk, in_keys=[in_key], out_keys=["features"])
            features = trunk.out_features
        if config.distribution not in DISTRIBUTIONS:
            raise SpecError(f"[ppo] distribution must be one of {', '.join(DISTRIBUTIONS)}, "
                            f"got {config.distribution!r}")
        outputs = action_dim if config.state_independent_std else 2 * action_dim
        scale = AddStateIndependentNormalScale(action_dim) if config.state_independent_std else NormalParamExtractor()
        policy_net = nn.Sequential(MLP(in_features=features, out_features=outputs, num_cells=config.hidden,
                                       activation_class=nn.Tanh), scale)
        last = policy_net[0][-1]
        with torch.no_grad():
            last.weight.mul_(config.policy_init_scale)
            last.bias.zero_()
        policy_head = TensorDictModule(policy_net, in_keys=["features"], out_keys=["loc", "scale"])
        value_net = MLP(in_features=features, out_features=1, num_cells=config.hidden, activation_class=nn.Tanh)
        value_head = ValueOperator(value_net, in_keys=["features"])
        actor = ProbabilisticActor(policy_head, in_keys=["loc", "scale"], spec=env.action_spec,
                                   distribution_class=DISTRIBUTIONS[config.distribution], return_log_prob=True)
        self.operator = ActorValueOperator(common, actor, value_head)

    @property
    def common(self) -> TensorDictModule:
        """The part both heads read: the observation normaliser, or the pixel trunk."""
        return self.operator.module[0]

    def trainable(self) -> list[nn.Parameter]:
        """The parameters PPO's optimiser updates and clips: trunk (if any), policy head, value head."""
        return list(self.operator.parameters())

    @property
    def policy(self) -> TensorDictModule:
        return self.operator.get_policy_operator()

    @property
    def value(self) -> TensorDictModule:
        return self.operator.get_value_operator()


def episode_returns(batch, num_envs: int, agent_steps: int) -> np.ndarray:
    """Undiscounted returns of the whole episodes in a batch [num_envs, episodes x agent_steps]."""
    reward = batch.get(("next", "reward")).reshape(num_envs, -1, agent_steps)
    return reward.sum(-1).flatten().double().cpu().numpy()


def ppo_objectives(nets: PolicyNetworks, config: PPOConfig, pixels: bool = False) -> tuple[ClipPPOLoss, GAE]:
    """The clipped PPO loss and the GAE estimator of `config`. GAE bootstraps from the critic where an
    episode is truncated (the time limit: `SuiteBatchEnv` marks it truncated, never terminated) and would
    not where one terminates."""
    # The loss gets the heads and `_update` runs the common part once per minibatch: a pixel trunk's forward
    # and backward are done once for both heads, not once per head (what is computed is the same).
    loss = ClipPPOLoss(nets.operator.get_policy_head(), nets.operator.get_value_head(),
                       clip_epsilon=config.clip_epsilon, clip_value=config.clip_value,
                       entropy_coeff=config.entropy_coeff, critic_coeff=config.critic_coeff,
                       loss_critic_type="l2", normalize_advantage=True)
    # With a pixel trunk the critic sees one environment's steps at a time: all of a batch's observations
    # and next observations at once (2 x 4,000 clips of 160x160) need more than 20 GB of CNN activations.
    advantage = GAE(gamma=config.gamma, lmbda=config.lmbda, value_network=nets.value, average_gae=False,
                    value_chunk_size=1 if pixels else None)
    return loss, advantage


def train_ppo(make_env: EnvFactory, config: PPOConfig, seed: int, workdir: Path,
              progress: Progress, trunk: nn.Module | None = None,
              device: torch.device | None = None) -> tuple[PolicyNetworks, TrainState]:
    """Train a policy; resumes from `workdir/ppo_checkpoint.pt` if a killed run left one.

    The environments step on the CPU; the networks, the losses and GAE run on `device` (the CPU by
    default): the collector moves each step's observation there and the action back."""
    device = device or torch.device("cpu")
    torch.manual_seed(seed)
    env = make_env(config.num_envs, seed)
    suite = suite_env_of(env)
    agent_steps = suite.config.agent_steps
    nets = PolicyNetworks(env, config, trunk).to(device)
    loss, advantage = ppo_objectives(nets, config, pixels=trunk is not None)
    optimizer = torch.optim.Adam(nets.trainable(), lr=config.lr)
    # Two units: agent steps (what the policy acts on; torchrl's collector counts these as its "frames")
    # and physics frames (agent steps x action repeat; what `config.frames` and the curves count).
    agent_steps_per_batch = config.num_envs * config.episodes_per_batch * agent_steps
    physics_frames_per_batch = agent_steps_per_batch * suite.config.action_repeat
    total_batches = max(1, math.ceil(config.frames / physics_frames_per_batch))

    state, rng = TrainState(), None
    workdir.mkdir(parents=True, exist_ok=True)
    checkpoint = workdir / "ppo_checkpoint.pt"
    if checkpoint.exists():
        state, rng, cuda_rng = _load_checkpoint(checkpoint, nets, optimizer, device)
    collector = Collector(env, nets.policy, frames_per_batch=agent_steps_per_batch,
                          total_frames=(total_batches - state.batch) * agent_steps_per_batch, reset_at_each_iter=True,
                          auto_register_policy_transforms=False, env_device="cpu", policy_device=device,
                          storing_device=device)
    if rng is not None:  # after the collector's construction, which may draw from it
        torch.set_rng_state(rng)
        restore_cuda_rng_state(cuda_rng)
    # Batch k's episodes start from initial states numbered k * episodes_per_batch, ... (see SuiteBatchEnv):
    # set before each rollout, whatever resets the collector made in between.
    suite.episode_index = state.batch * config.episodes_per_batch
    began = time.monotonic() - state.wall_s
    for batch in collector:
        returns = episode_returns(batch, config.num_envs, agent_steps)
        if config.anneal_lr:
            for group in optimizer.param_groups:
                group["lr"] = config.lr * (1.0 - state.batch / total_batches)
        stats = _update(batch, nets.common, loss, advantage, optimizer, config)
        # After the update: its importance ratios compare log-probabilities under the statistics the batch
        # was collected with; the next batch is collected with the new ones.
        if nets.normalizer is not None:
            nets.normalizer.update(batch.get("observation"))
        # The collector may act with a copy of the policy (another device); it collects the next batch
        # with the weights (and observation statistics) just learnt either way.
        collector.update_policy_weights_()
        state.batch += 1
        state.frames += physics_frames_per_batch
        state.wall_s = time.monotonic() - began
        state.curve_frames.append(float(state.frames))
        state.curve_wall_s.append(state.wall_s)
        state.curve_return.append(float(returns.mean()))
        for name, key in DIAGNOSTICS.items():
            if key in stats:  # the entropy only where the loss has an entropy bonus
                state.diagnostics.setdefault(name, []).append(stats[key])
        if state.batch % config.checkpoint_every == 0 or state.batch == total_batches:
            _save_checkpoint(checkpoint, nets, optimizer, state)
        progress(state.batch, total_batches, {"return": float(returns.mean()), **stats})
        suite.episode_index = state.batch * config.episodes_per_batch
    collector.shutdown()
    return nets, state


def _update(batch, common: Callable[[TensorDictBase], TensorDictBase], loss: ClipPPOLoss, advantage: GAE,
            optimizer: torch.optim.Optimizer, config: PPOConfig) -> dict[str, float]:
    """`epochs` passes of shuffled minibatches; each minibatch goes through `common` (the heads' shared
    input) once, then the loss of both heads."""
    batch = batch.clone()  # on the policy's device (the collector's storing_device)
    batch.set(("next", "reward"), batch.get(("next", "reward")) * config.reward_scale)
    with torch.no_grad():
        advantage(batch)
    flat = batch.reshape(-1)
    n = flat.shape[0]
    totals: dict[str, float] = {}
    count = 0
    for _ in range(config.epochs):
        for index in torch.randperm(n).split(config.minibatch_size):
            parts = loss(common(flat[index]))
            total = parts["loss_objective"] + parts["loss_critic"] + parts.get("loss_entropy", 0.0)
            if not torch.isfinite(total):
                raise TrainingError(f"PPO loss became {float(total)}; stopping without a result")
            optimizer.zero_grad()
            total.backward()
            nn.utils.clip_grad_norm_(optimizer.param_groups[0]["params"], config.max_grad_norm)
            optimizer.step()
            for key in ("loss_objective", "loss_critic", *DIAGNOSTICS.values()):
                if key in parts.keys():
                    totals[key] = totals.get(key, 0.0) + float(parts[key].detach().mean())
            count += 1
    return {k: v / count for k, v in totals.items()}


def _save_checkpoint(path: Path, nets: PolicyNetworks, optimizer: torch.optim.Optimizer,
                     state: TrainState) -> None:
    import io

    payload = {"nets": nets.state_dict(), "optimizer": optimizer.state_dict(), "state": asdict(state),
               "torch_rng": torch.get_rng_state(), "cuda_rng": cuda_rng_state()}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def _load_checkpoint(path: Path, nets: PolicyNetworks, optimizer: torch.optim.Optimizer,
                     device: torch.device) -> tuple[TrainState, torch.Tensor, list[torch.Tensor]]:
    try:
        payload = torch.load(path, weights_only=True, map_location=device)
        nets.load_state_dict(payload["nets"])
        optimizer.load_state_dict(payload["optimizer"])
        return TrainState(**payload["state"]), payload["torch_rng"].cpu(), payload.get("cuda_rng", [])
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint gets the same one-line answer
        raise TrainingError(f"PPO checkpoint {path} cannot be read ({type(exc).__name__}); delete it or rerun "
                            f"with --force to train from the start") from None


EVAL_SEED_OFFSET = 1_000_003  # the test environments' seed is the run's plus this: apart from training's seeds


@torch.no_grad()
def evaluate_policy(make_env: EnvFactory, nets: PolicyNetworks, episodes: int,
                    num_envs: int, seed: int, device: torch.device | None = None) -> np.ndarray:
    """Returns of `episodes` test episodes with the policy's deterministic (mean) action, on environments
    seeded apart from training; the policy runs on `device` (where `nets` are), the environments on the CPU."""
    eval_env = make_env(num_envs, seed + EVAL_SEED_OFFSET)
    steps = suite_env_of(eval_env).config.agent_steps
    returns: list[float] = []
    try:
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            while len(returns) < episodes:
                rollout = eval_env.rollout(steps, nets.policy, break_when_any_done=False,
                                           auto_cast_to_device=device is not None and device.type != "cpu")
                returns.extend(rollout.get(("next", "reward")).sum(dim=(1, 2)).double().tolist())
    finally:
        eval_env.close()
    return np.asarray(returns[:episodes])
