"""Diagnostic: how much of a control task's true state does a fitted encoder's embedding carry?

Loads (or fits, when it is not cached yet) the encoder of `mftcn-bench run --encoder E --task T --preset P`,
embeds every episode of the task's dataset from the camera the policy sees, and fits the cartpole-probe's MLP
(scikit-learn, features [e_t, e_t - e_{t-1}], `tasks/cartpole-probe.toml`'s [probe] table) to the standardised
simulator state (as true-state embeds it: a cartpole angle as its sine and cosine) on the train split. Prints
R^2 per state dimension on the test split and the mean. Used to tell "the embedding does not carry the state"
apart from "PPO does not learn from it" for a control row that falls short of the paper (see the note on the
cheetah mftcn5 row in the README). It reads the dataset the encoder was trained on; for a task whose dataset
is an expert's demonstrations (cheetah), `--random-episodes N` also records N episodes of uniformly random
actions (held for the action repeat) and prints the same probe's R^2 on them: states the demonstrations never
visit, like a PPO agent's early ones.

    MFTCN_BENCH_HOME=... python docs/diagnostics/embedding_state_probe.py --encoder mftcn5 --task cheetah \
        --preset quick --random-episodes 4
"""

from __future__ import annotations

import argparse
import warnings
from collections.abc import Iterable
from dataclasses import replace

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.metrics import r2_score
from sklearn.preprocessing import StandardScaler

from mftcn_bench.core import registry
from mftcn_bench.core.home import BenchHome
from mftcn_bench.encoders.base import Encoder, embed_episode
from mftcn_bench.encoders.baselines import state_embedding
from mftcn_bench.rl.demos import ExpertDemoCollector
from mftcn_bench.run.runner import PreparedRun, RunRequest, build_encoder, prepare, prepare_dataset
from mftcn_bench.sim.rendering import ensure_gl
from mftcn_bench.tasks.probe import ProbeConfig, probe_features, probe_regressor


def features(encoder: Encoder, episodes: Iterable[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, ...]:
    """Probe features, state targets and episode numbers of every frame of (frames of one view, states)
    episodes."""
    xs, ys, names = [], [], []
    for number, (frames, state) in enumerate(episodes):
        xs.append(probe_features(embed_episode(encoder, frames, state)))
        ys.append(state_embedding(state))
        names.append(np.full(len(state), number))
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(names)


class UniformPolicy:
    """Uniformly random actions in [-1, 1] (the suite's action bounds for cartpole and cheetah)."""

    def __init__(self, dim: int, seed: int) -> None:
        self.dim, self.rng = dim, np.random.default_rng(seed)

    def act(self, state: np.ndarray) -> np.ndarray:
        return self.rng.uniform(-1.0, 1.0, self.dim)


def random_action_collector(prepared: PreparedRun) -> ExpertDemoCollector:
    """The task's demonstration collector with uniformly random actions in place of the expert's."""
    demos = prepared.task.collector
    if not isinstance(demos, ExpertDemoCollector):
        raise SystemExit(f"--random-episodes needs a task whose dataset is an expert's demonstrations "
                         f"(cheetah); {prepared.request.task!r}'s is not")
    ensure_gl()  # before dm_control is imported: it picks its OpenGL back end then
    from dm_control import suite

    dim = suite.load(prepared.task.dataset_config["domain"], demos.env_config.task).action_spec().shape[0]
    return ExpertDemoCollector(demos.expert_path, demos.env_config, demos.ppo,
                               policy=UniformPolicy(dim, prepared.request.seed))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--encoder", required=True)
    parser.add_argument("--task", required=True, help="a control task (swingup, swingup-moving, cheetah, ...)")
    parser.add_argument("--preset", default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--random-episodes", type=int, default=0, help="also probe N random-action episodes")
    args = parser.parse_args()
    if args.random_episodes < 0:
        parser.error(f"--random-episodes must be >= 0, got {args.random_episodes}")

    # This probe reads the task's data whatever the encoder (a run of true state on swing-up reads none).
    prepared = replace(prepare(RunRequest(args.encoder, args.task, args.preset, args.seed)), reads_data=True)
    home = BenchHome.resolve()
    dataset = prepare_dataset(prepared, home, show_progress=False)
    randomised = random_action_collector(prepared) if args.random_episodes else None
    encoder, _ = build_encoder(prepared, dataset, home, show_progress=False)
    camera = prepared.config["task"]["env"]["camera"]
    view = dataset.cameras.index(camera)
    x_train, y_train, groups = features(encoder, ((e.frames[view], e.state) for e in dataset.iter_episodes("train")))
    x_test, y_test, _ = features(encoder, ((e.frames[view], e.state) for e in dataset.iter_episodes("test")))

    probe = ProbeConfig(**registry.get("tasks", "cartpole-probe").spec.tables["probe"])
    scale = StandardScaler().fit(y_train)
    regressor = probe_regressor(probe, args.seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        regressor.fit(x_train, scale.transform(y_train), groups)
    print(f"{args.encoder} on {args.task} ({prepared.preset}): camera {camera!r}, {len(x_train)} train and "
          f"{len(x_test)} test frames, {y_train.shape[1]} state dimensions")
    report("test split", scale.transform(y_test), regressor.predict(x_test))
    if randomised is not None:  # episode indices past the dataset's, so other initial states
        episodes = (randomised(dataset.config, 1_000_000 + i) for i in range(args.random_episodes))
        x_random, y_random, _ = features(encoder, ((e["frames"][view], e["state"]) for e in episodes))
        report(f"{args.random_episodes} random-action episodes ({len(x_random)} frames)",
               scale.transform(y_random), regressor.predict(x_random))


def report(what: str, truth: np.ndarray, predicted: np.ndarray) -> None:
    """R^2 per standardised state dimension, and their mean."""
    r2 = r2_score(truth, predicted, multioutput="raw_values")
    print(f"{what}: R^2 per dimension " + " ".join(f"{v:.2f}" for v in r2))
    print(f"{what}: mean R^2 {r2.mean():.3f} (min {r2.min():.2f}, max {r2.max():.2f})")


if __name__ == "__main__":
    main()
