"""Diagnostic: where do a finished cartpole run's test episodes take the cart, and does its camera see it?

Loads the encoder and the final PPO networks of a finished run (`mftcn-bench run --encoder E --task T
--preset P --seed S`, its folder `runs/<id>` in the home), plays at least `--episodes` test episodes (whole
rounds of up to the test's number of environments) with the policy's mean action on the test's environments
(the run's own evaluation seeds, so the returns printed should be the record's first test returns), records
the cart's position and the pole's angle at every frame of the stream, and prints the distribution of |x| and
how often the task's camera cuts the cart or the pole (`camera_coverage.py`, beside this file). Used to tell
whether the fixed camera's square 160x160 image, which cuts the cart in most frames of the random-action data,
also cuts it where the policy drives it.

    MFTCN_BENCH_HOME=... python docs/diagnostics/policy_cart_range.py --encoder mftcn5 --task swingup-160 \
        --preset paper --seed 0 [--episodes 8]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
from camera_coverage import cartpole_physics, coverage
from tensordict import TensorDictBase
from torchrl.envs import ExplorationType, Transform, set_exploration_type

from mftcn_bench.core.home import BenchHome
from mftcn_bench.rl.ppo import EVAL_SEED_OFFSET, PolicyNetworks
from mftcn_bench.rl.suite_env import suite_env_of
from mftcn_bench.run.runner import RunRequest, build_encoder, prepare, prepare_dataset, run_id_of
from mftcn_bench.tasks.control import PPOTask


class StateRecorder(Transform):
    """Keeps the simulator state of every frame of the stream an environment emits ([E, k, S] a step)."""

    def __init__(self) -> None:
        super().__init__(in_keys=[], out_keys=[])
        self.states: list[np.ndarray] = []

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self.states.append(tensordict_reset.get("state")[:, -1:].numpy().copy())  # the first frame, repeated
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self.states.append(next_tensordict.get("state").numpy().copy())
        return next_tensordict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--encoder", required=True)
    parser.add_argument("--task", required=True, help="a cartpole control task (swingup, swingup-160, ...)")
    parser.add_argument("--preset", default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=8)
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")

    prepared = prepare(RunRequest(args.encoder, args.task, args.preset, args.seed))
    task = prepared.task
    if not isinstance(task, PPOTask) or task.env_config.domain != "cartpole":
        raise SystemExit(f"--task must be a cartpole control task; {args.task!r} is not")
    home = BenchHome.resolve()
    dataset = prepare_dataset(prepared, home, show_progress=False) if prepared.reads_data else None
    run_dir = home.runs / run_id_of(prepared, None if dataset is None else dataset.fingerprint)
    checkpoint = run_dir / "ppo_checkpoint.pt"
    if not (run_dir / "result.json").exists() or not checkpoint.exists():
        raise SystemExit(f"no finished run with a PPO checkpoint in {run_dir}; run `mftcn-bench run --encoder "
                         f"{args.encoder} --task {args.task} --preset {prepared.preset} --seed {args.seed}` first "
                         f"(with the code that made it)")
    encoder, _ = build_encoder(prepared, dataset, home, show_progress=False)
    # The run's own environment factory, so that the replay sees exactly what the policy saw.
    make_env, trunk = task._env_factory(encoder)
    num_envs = min(task.ppo.num_envs, args.episodes)
    env = make_env(num_envs, args.seed + EVAL_SEED_OFFSET)
    nets = PolicyNetworks(env, task.ppo, trunk)
    nets.load_state_dict(torch.load(checkpoint, map_location="cpu", weights_only=False)["nets"])
    recorder = StateRecorder()
    env.transform.insert(0, recorder)
    returns: list[float] = []
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        while len(returns) < args.episodes:
            rollout = env.rollout(suite_env_of(env).config.agent_steps, nets.policy, break_when_any_done=False)
            returns.extend(rollout.get(("next", "reward")).sum(dim=(1, 2)).double().tolist())
    env.close()
    states = np.concatenate(recorder.states, axis=1).reshape(-1, recorder.states[0].shape[-1])

    record = json.loads((run_dir / "result.json").read_text())
    stored = record["curves"]["test"]["return"][:len(returns)]
    print(f"{args.encoder} on {args.task} ({prepared.preset}, seed {args.seed}), run {run_dir.name}: "
          f"{len(returns)} test episodes, {len(states)} frames")
    print("returns replayed: " + " ".join(f"{r:.1f}" for r in returns))
    print("returns stored:   " + " ".join(f"{r:.1f}" for r in stored))
    distance = np.abs(states[:, 0])
    print(f"|x| median {np.median(distance):.3f}, 90th percentile {np.quantile(distance, 0.9):.3f}, "
          f"max {distance.max():.3f}")
    config = task.env_config
    seen = coverage(cartpole_physics(), config.camera, config.height, config.width, states)
    print(f"{config.camera} at {config.width}x{config.height}: cart cut by the edge {seen.cart_cut.mean():.3f}, "
          f"cart centre outside {seen.cart_centre_out.mean():.3f}, pole tip outside {seen.tip_out.mean():.3f}")


if __name__ == "__main__":
    main()
