"""cartpole-probe: how well a frozen embedding encodes the cartpole's true state.

Protocol of the paper (after PVE): features [e_t, e_t - e_{t-1}] of one camera's clips (at an episode's
first frame the difference is zero); an MLP with three hidden layers of 256 trained with Adam (lr 1e-3)
regresses x_cart, sin(theta), cos(theta), x_dot, theta_dot on the train split; MSE per attribute on the
test split, Position = mean of the three static ones, Motion = mean of the two velocities, Average = all
five. The MLP fits standardised targets (`standardize_targets`: each target weighs the same in its loss)
and a tenth of the train split's episodes, whole, is held out to stop its training when it stops improving
(so uninformative features are not memorised). Beside each MSE: R^2 and the MSE of predicting the train
targets' mean. MSEs are on the simulator's scale (metres, radians per second), as in the paper; the test
targets' variance is stored beside them so a reader can tell how much of it is explained.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.metrics import mean_squared_error, r2_score
from sklearn.neural_network import MLPRegressor
from sklearn.preprocessing import StandardScaler

from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.specs import parse_table
from mftcn_bench.data.cartpole import TARGETS, camera_names, collect_episode, state_targets
from mftcn_bench.data.dataset import Collector, MultiViewDataset
from mftcn_bench.encoders.base import Encoder, embed_episode
from mftcn_bench.sim.suite_limits import check_dataset_fits
from mftcn_bench.tasks.base import TaskResult

POSITION, MOTION = TARGETS[:3], TARGETS[3:]


@dataclass(frozen=True)
class ProbeConfig:
    """The `[probe]` table of the task spec."""

    camera: str
    hidden: list[int]
    lr: float
    epochs: int
    batch_size: int
    tol: float
    early_stopping: bool
    validation_fraction: float
    patience: int
    standardize_targets: bool = True

    def __post_init__(self) -> None:
        """Refuse values the MLP would reject only after the dataset and the encoder are made."""
        fraction = self.validation_fraction
        rules = {"epochs": self.epochs >= 1, "batch_size": self.batch_size >= 1, "patience": self.patience >= 1,
                 "lr": self.lr > 0, "tol": self.tol >= 0,
                 "validation_fraction": 0 <= fraction < 1 and (fraction > 0 or not self.early_stopping),
                 "hidden": bool(self.hidden) and all(h >= 1 for h in self.hidden)}
        allowed = {"epochs": ">= 1", "batch_size": ">= 1", "patience": ">= 1", "lr": "> 0", "tol": ">= 0",
                   "validation_fraction": "in [0, 1), and > 0 with early_stopping",
                   "hidden": "a non-empty list of sizes >= 1"}
        for key, ok in rules.items():
            if not ok:
                raise SpecError(f"task.probe.{key} must be {allowed[key]}, got {getattr(self, key)}")


def probe_features(embeddings: np.ndarray) -> np.ndarray:
    """[e_t, e_t - e_{t-1}] for one episode; the first frame's difference is zero."""
    previous = np.concatenate([embeddings[:1], embeddings[:-1]])
    return np.concatenate([embeddings, embeddings - previous], axis=1)


class ProbeMLP:
    """The probe's MLP: standardised features and standardised targets (so that theta_dot, variance ~16,
    does not outweigh sin and cos theta, ~0.4, in the loss), Adam epochs (`partial_fit`), and early stopping
    on whole held-out episodes (random held-out frames have neighbours one frame away in the training part).
    Predictions are on the simulator's scale. sklearn's own early stopping holds out random rows and cannot
    be given groups, hence this loop; the network and optimiser are sklearn's."""

    def __init__(self, probe: ProbeConfig, seed: int) -> None:
        self.probe, self.seed = probe, seed
        self.x_scale, self.y_scale = StandardScaler(), StandardScaler()
        self.mlp = MLPRegressor(hidden_layer_sizes=tuple(probe.hidden), solver="adam",
                                learning_rate_init=probe.lr, batch_size=probe.batch_size, shuffle=True,
                                random_state=seed)
        self.n_iter_ = 0

    def held_out(self, episodes: np.ndarray) -> np.ndarray:
        """Which rows form the early-stopping hold-out: a `validation_fraction` of the episodes (at least one,
        never all)."""
        names = np.unique(episodes)
        if not self.probe.early_stopping or len(names) < 2:
            return np.zeros(len(episodes), dtype=bool)
        count = min(max(1, round(self.probe.validation_fraction * len(names))), len(names) - 1)
        picked = np.random.default_rng(self.seed).choice(names, size=count, replace=False)
        return np.isin(episodes, picked)

    def fit(self, x: np.ndarray, y: np.ndarray, episodes: np.ndarray) -> ProbeMLP:
        """Fit on rows `x` [N, F], targets `y` [N, T], `episodes` [N] naming each row's episode."""
        hold = self.held_out(episodes)
        xs = self.x_scale.fit(x[~hold]).transform(x)
        self.y_scale.set_params(with_mean=self.probe.standardize_targets, with_std=self.probe.standardize_targets)
        ys = self.y_scale.fit(y[~hold]).transform(y)
        best, best_loss, waited = None, np.inf, 0
        for epoch in range(self.probe.epochs):
            self.mlp.partial_fit(xs[~hold], ys[~hold])
            self.n_iter_ = epoch + 1
            if not hold.any():
                continue
            loss = float(np.mean((self.mlp.predict(xs[hold]) - ys[hold]) ** 2))
            if loss < best_loss - self.probe.tol:
                best_loss, waited = loss, 0
                best = ([w.copy() for w in self.mlp.coefs_], [b.copy() for b in self.mlp.intercepts_])
            else:
                waited += 1
                if waited >= self.probe.patience:
                    break
        if best is not None:  # the epoch with the lowest held-out loss, as sklearn's early stopping keeps
            self.mlp.coefs_, self.mlp.intercepts_ = best
        return self

    def predict(self, x: np.ndarray) -> np.ndarray:
        out = self.mlp.predict(self.x_scale.transform(x))
        return self.y_scale.inverse_transform(out.reshape(len(x), -1))


def probe_regressor(probe: ProbeConfig, seed: int) -> ProbeMLP:
    """The probe's regressor (one definition, used by cartpole-probe, swingup-probe-state and the
    state-probe diagnostic)."""
    return ProbeMLP(probe, seed)


def probe_split(encoder: Encoder, dataset: MultiViewDataset, camera: str,
                split: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Probe features [e_t, e_t - e_{t-1}] of `camera`, state targets (TARGETS order) and each row's episode
    index, for every episode of one split."""
    view = dataset.cameras.index(camera)
    xs, ys, names = [], [], []
    for episode in dataset.iter_episodes(split):
        embeddings = embed_episode(encoder, episode.frames[view], episode.state)
        xs.append(probe_features(embeddings))
        ys.append(state_targets(episode.state))
        names.append(np.full(len(embeddings), episode.index))
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(names)


def fit_probe(probe: ProbeConfig, seed: int, x: np.ndarray, y: np.ndarray, episodes: np.ndarray) -> ProbeMLP:
    """The probe's regressor fitted on rows `x`, targets `y` and their `episodes` (sklearn's warning that
    the epoch budget ran out is expected: early stopping, not convergence, ends the fit)."""
    regressor = probe_regressor(probe, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return regressor.fit(x, y, episodes)


def summarize(mse: Mapping[str, float]) -> dict[str, float]:
    """Per-attribute MSE plus Position, Motion and Average means."""
    out = {f"mse_{k}": float(mse[k]) for k in TARGETS}
    out["position"] = float(np.mean([mse[k] for k in POSITION]))
    out["motion"] = float(np.mean([mse[k] for k in MOTION]))
    out["average"] = float(np.mean([mse[k] for k in TARGETS]))
    return out


class CartpoleProbe:
    """MLP regression of the cartpole's true state from [e_t, e_t - e_{t-1}]."""

    def __init__(self, config: Mapping[str, Any], seed: int) -> None:
        self.config, self.seed = config, seed
        self.probe = parse_table(ProbeConfig, f"task {config['name']!r}", "probe", config["probe"])
        check_dataset_fits("cartpole", "swingup", config["dataset"], f"task {config['name']!r}: [dataset]")
        available = camera_names()
        unknown = [c for c in config["dataset"]["cameras"] if c not in available]
        if unknown:
            raise SpecError(f"camera {unknown[0]!r} does not exist in cartpole; available: {', '.join(available)}")
        if self.probe.camera not in config["dataset"]["cameras"]:
            raise SpecError(f"probe camera {self.probe.camera!r} is not one of the dataset's cameras "
                            f"{config['dataset']['cameras']}")

    @property
    def dataset_config(self) -> Mapping[str, Any]:
        return self.config["dataset"]

    @property
    def collector(self) -> Collector:
        return collect_episode

    def features(self, encoder: Encoder, dataset: MultiViewDataset, split: str) -> tuple[np.ndarray, ...]:
        """Probe features, targets and each row's episode index for one split (the probe-memory benchmark
        wraps this to time and size the embedding phase)."""
        return probe_split(encoder, dataset, self.probe.camera, split)

    def evaluate(self, encoder: Encoder, dataset: MultiViewDataset, workdir: Path | None = None) -> TaskResult:
        x_train, y_train, episodes = self.features(encoder, dataset, "train")
        x_test, y_test, _ = self.features(encoder, dataset, "test")
        regressor = fit_probe(self.probe, self.seed, x_train, y_train, episodes)
        predicted = regressor.predict(x_test)
        mse = mean_squared_error(y_test, predicted, multioutput="raw_values")
        metrics: dict[str, float | None] = summarize(dict(zip(TARGETS, mse, strict=True)))
        r2 = r2_score(y_test, predicted, multioutput="raw_values")
        metrics.update({f"r2_{k}": float(v) for k, v in zip(TARGETS, r2, strict=True)})
        metrics.update({f"var_{k}": float(v) for k, v in zip(TARGETS, y_test.var(axis=0), strict=True)})
        mean_mse = mean_squared_error(y_test, np.broadcast_to(y_train.mean(axis=0), y_test.shape),
                                      multioutput="raw_values")  # the reference: predict the train mean
        metrics.update({f"mean_predictor_{k}": float(v) for k, v in zip(TARGETS, mean_mse, strict=True)})
        metrics["mean_predictor_average"] = float(mean_mse.mean())
        metrics.update({"train_frames": float(len(x_train)), "test_frames": float(len(x_test)),
                        "probe_epochs": float(regressor.n_iter_)})
        notes = [f"MSE on the simulator's scale (x in m, velocities in m/s and rad/s); {len(x_train)} train "
                 f"and {len(x_test)} test frames from camera {self.probe.camera!r}."]
        return TaskResult(metrics, notes)

    def table(self, metrics: Mapping[str, Any]) -> list[dict[str, Any]]:
        rows = [{"attribute": k, "MSE": metrics[f"mse_{k}"], "R^2": metrics.get(f"r2_{k}"),
                 "mean of train targets": metrics.get(f"mean_predictor_{k}"), "test variance": metrics[f"var_{k}"]}
                for k in TARGETS]  # records made before R^2 and the mean reference were stored have neither
        rows += [{"attribute": name.capitalize(), "MSE": metrics[name], "R^2": None,
                  "mean of train targets": metrics.get("mean_predictor_average") if name == "average" else None,
                  "test variance": None} for name in ("position", "motion", "average")]
        return rows
