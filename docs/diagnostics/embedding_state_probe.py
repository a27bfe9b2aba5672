"""Diagnostic: how much of a control task's true state does a fitted encoder's embedding carry?

Loads (or fits, when it is not cached yet) the encoder of `mftcn-bench run --encoder E --task T --preset P`,
embeds every episode of the task's dataset from the camera the policy sees, and fits the cartpole-probe's
MLP (scikit-learn, features [e_t, e_t - e_{t-1}], `tasks/cartpole-probe.toml`'s [probe] table) to the
standardised simulator state (as true-state embeds it: a cartpole angle as its sine and cosine) on the train
split. Prints R^2 per state dimension on the test split and the
mean. Used to tell "the embedding does not carry the state" apart from "PPO does not learn from it" for a
control row that falls short of the paper (see the note on the cheetah mftcn5 row in the README). It reads
only the dataset the encoder was trained on, so it says nothing about states the demonstrations never visit.

    MFTCN_BENCH_HOME=... python docs/diagnostics/embedding_state_probe.py --encoder mftcn5 --task cheetah \
        --preset quick
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.metrics import r2_score
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from mftcn_bench import registry
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import Encoder, embed_episode
from mftcn_bench.encoders.baselines import state_embedding
from mftcn_bench.home import BenchHome
from mftcn_bench.runner import RunRequest, build_encoder, prepare, prepare_dataset
from mftcn_bench.tasks.probe import ProbeConfig, probe_features


def features(encoder: Encoder, dataset: MultiViewDataset, view: int, split: str) -> tuple[np.ndarray, np.ndarray]:
    """Probe features and state targets of every frame of one split, seen from camera `view`."""
    xs, ys = [], []
    for episode in dataset.iter_episodes(split):
        xs.append(probe_features(embed_episode(encoder, episode.frames[view], episode.state)))
        ys.append(state_embedding(episode.state))
    return np.concatenate(xs), np.concatenate(ys)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--encoder", required=True)
    parser.add_argument("--task", required=True, help="a control task (swingup, swingup-moving, cheetah, ...)")
    parser.add_argument("--preset", default=None)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    prepared = prepare(RunRequest(args.encoder, args.task, args.preset, args.seed))
    home = BenchHome.resolve()
    dataset = prepare_dataset(prepared, home, show_progress=False)
    encoder, _ = build_encoder(prepared, dataset, home, show_progress=False)
    camera = prepared.config["task"]["env"]["camera"]
    view = dataset.cameras.index(camera)
    x_train, y_train = features(encoder, dataset, view, "train")
    x_test, y_test = features(encoder, dataset, view, "test")

    probe = ProbeConfig(**registry.get("tasks", "cartpole-probe").spec.tables["probe"])
    scale = StandardScaler().fit(y_train)
    regressor = make_pipeline(StandardScaler(), MLPRegressor(
        hidden_layer_sizes=tuple(probe.hidden), solver="adam", learning_rate_init=probe.lr,
        batch_size=probe.batch_size, max_iter=probe.epochs, tol=probe.tol, early_stopping=probe.early_stopping,
        validation_fraction=probe.validation_fraction, n_iter_no_change=probe.patience, random_state=args.seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        regressor.fit(x_train, scale.transform(y_train))
    r2 = r2_score(scale.transform(y_test), regressor.predict(x_test), multioutput="raw_values")
    print(f"{args.encoder} on {args.task} ({prepared.preset}): camera {camera!r}, {len(x_train)} train and "
          f"{len(x_test)} test frames, {y_train.shape[1]} state dimensions")
    print("R^2 per dimension: " + " ".join(f"{v:.2f}" for v in r2))
    print(f"mean R^2 {r2.mean():.3f} (min {r2.min():.2f}, max {r2.max():.2f})")


if __name__ == "__main__":
    main()
