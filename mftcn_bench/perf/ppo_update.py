"""The pixel-trunk PPO update figure: `rl.ppo._update` on a batch of cheetah clips with the pixels-cnn trunk
(run once per minibatch for both heads, channels-last weights), against torchrl's ClipPPOLoss given the
whole actor and critic operators (each head runs the trunk itself; weights in the default layout).

Work is minibatches of the task's size (512 clips of 64x64): a cheetah seed at the paper preset makes
188 batches x 10 epochs x 8 of them, so this figure times the largest part of a pixels-cnn run.
"""

from __future__ import annotations

import copy
import math
from dataclasses import replace

from mftcn_bench.perf.timing import BenchRow, Sizes, Target, alternate, one_thread, timed


def _batch(make_env, nets, agent_steps: int, num_envs: int):
    """One collected batch of `num_envs` x `agent_steps` steps of `nets`'s policy (untrained)."""
    from torchrl.collectors import Collector

    collector = Collector(make_env(num_envs, 0), nets.policy, frames_per_batch=num_envs * agent_steps,
                          total_frames=num_envs * agent_steps, reset_at_each_iter=True,
                          auto_register_policy_transforms=False)
    try:
        return next(iter(collector))
    finally:
        collector.shutdown()


def bench_ppo_update_pixels(sizes: Sizes) -> list[BenchRow]:
    """Minibatches/s of the harness's PPO update on pixels-cnn clips against the trunk-per-head update."""
    import torch
    from torch import nn
    from torchrl.objectives import ClipPPOLoss

    from mftcn_bench.core.specs import encoder_spec_from_config
    from mftcn_bench.rl.ppo import PolicyNetworks, _update, ppo_objectives
    from mftcn_bench.run.plan import RunRequest, prepare
    from mftcn_bench.tasks.control import ClipTrunk

    one_thread()
    prepared = prepare(RunRequest("pixels-cnn", "cheetah", "paper", 0))
    task, data = prepared.task, prepared.task.dataset_config
    spec = encoder_spec_from_config(prepared.encoder_entry.description, prepared.config["encoder"])
    encoder = prepared.encoder_entry.load()(spec, image_shape=(data["height"], data["width"]), seed=0)
    config = replace(task.ppo, epochs=1)  # one pass over the batch per timed block
    num_envs = 8
    agent_steps = math.ceil(config.minibatch_size * sizes.ppo_update_minibatches / num_envs)
    make_env, trunk = task.env_factory(encoder)
    env = make_env(num_envs, 0)

    torch.manual_seed(0)
    nets = PolicyNetworks(env, config, trunk)
    loss, advantage = ppo_objectives(nets, config, pixels=True)
    optimizer = torch.optim.Adam(nets.trainable(), lr=config.lr)

    reference_trunk = ClipTrunk(copy.deepcopy(encoder.net), trunk.out_features)
    reference_trunk.net.to(memory_format=torch.contiguous_format)
    torch.manual_seed(0)
    reference = PolicyNetworks(env, config, reference_trunk)
    env.close()
    reference_loss = ClipPPOLoss(reference.policy, reference.value, clip_epsilon=config.clip_epsilon,
                                 clip_value=config.clip_value, entropy_coeff=config.entropy_coeff,
                                 critic_coeff=config.critic_coeff, loss_critic_type="l2", normalize_advantage=True)
    reference_optimizer = torch.optim.Adam(reference_loss.parameters(), lr=config.lr)

    batch = _batch(make_env, nets, agent_steps, num_envs)
    minibatches = float(math.ceil(batch.numel() / config.minibatch_size))
    rates = alternate({
        "harness": timed(lambda: _update(batch, nets.common, loss, advantage, optimizer, config), minibatches),
        "reference": timed(lambda: _update(batch, nn.Identity(), reference_loss, advantage, reference_optimizer,
                                           config), minibatches)}, sizes.rounds)
    # What one seed at the paper preset updates: its batches x epochs x minibatches of a batch.
    paper, env_config = task.ppo, task.env_config
    batch_steps = paper.num_envs * paper.episodes_per_batch * (env_config.episode_length // env_config.action_repeat)
    per_seed = (math.ceil(paper.frames / (batch_steps * env_config.action_repeat)) * paper.epochs
                * math.ceil(batch_steps / paper.minibatch_size))
    note = (f"{int(minibatches)} minibatch(es) of {config.minibatch_size} clips a block; a cheetah seed at the "
            f"paper preset updates {per_seed:,} of them: {per_seed / rates['harness'] / 3600:.2f} h here")
    return [BenchRow(f"PPO update on pixels-cnn clips (cheetah 64x64, minibatch {config.minibatch_size})",
                     rates["harness"], "minibatches/s", "each head running the trunk, default layout",
                     rates["reference"], rates["harness"] / rates["reference"], Target(">=", 2.0), note)]
