"""cartpole-probe: how well a frozen embedding encodes the cartpole's true state.

Protocol of the paper (after PVE): features [e_t, e_t - e_{t-1}] of one camera's clips (at an episode's
first frame the difference is zero); an MLP with three hidden layers of 256 trained with Adam (lr 1e-3)
regresses x_cart, sin(theta), cos(theta), x_dot, theta_dot on the train split; MSE per attribute on the
test split, Position = mean of the three static ones, Motion = mean of the two velocities, Average = all
five. A tenth of the train split is held out to stop the MLP's training when it stops improving (so
uninformative features are not memorised). Targets are on the simulator's scale (metres, radians per
second), as in the paper; the test targets' variance is stored beside each MSE so a reader can tell how
much of it is explained.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.metrics import mean_squared_error
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import Pipeline, make_pipeline
from sklearn.preprocessing import StandardScaler

from mftcn_bench.data.cartpole import camera_names, collect_episode
from mftcn_bench.data.dataset import Collector, MultiViewDataset
from mftcn_bench.encoders.base import Encoder, embed_episode
from mftcn_bench.errors import SpecError
from mftcn_bench.tasks.base import TaskResult

TARGETS = ("x_cart", "sin_theta", "cos_theta", "x_dot", "theta_dot")
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


def state_targets(state: np.ndarray) -> np.ndarray:
    """Simulator state [T, 4] (x, theta, x_dot, theta_dot) -> targets [T, 5] in TARGETS order."""
    x, theta, x_dot, theta_dot = state.T
    return np.stack([x, np.sin(theta), np.cos(theta), x_dot, theta_dot], axis=1)


def probe_features(embeddings: np.ndarray) -> np.ndarray:
    """[e_t, e_t - e_{t-1}] for one episode; the first frame's difference is zero."""
    previous = np.concatenate([embeddings[:1], embeddings[:-1]])
    return np.concatenate([embeddings, embeddings - previous], axis=1)


def probe_regressor(probe: ProbeConfig, seed: int) -> Pipeline:
    """The probe's MLP (Adam, early stopping on a held-out fraction) behind a feature standardiser."""
    return make_pipeline(StandardScaler(), MLPRegressor(
        hidden_layer_sizes=tuple(probe.hidden), solver="adam", learning_rate_init=probe.lr,
        batch_size=probe.batch_size, max_iter=probe.epochs, tol=probe.tol, early_stopping=probe.early_stopping,
        validation_fraction=probe.validation_fraction, n_iter_no_change=probe.patience, random_state=seed,
        shuffle=True))


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
        try:
            self.probe = ProbeConfig(**config["probe"])
        except TypeError as exc:
            raise SpecError(f"task {config['name']!r}: bad [probe] table ({exc})") from None
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
        view = dataset.cameras.index(self.probe.camera)
        xs, ys = [], []
        for episode in dataset.iter_episodes(split):
            embeddings = embed_episode(encoder, episode.frames[view], episode.state)
            xs.append(probe_features(embeddings))
            ys.append(state_targets(episode.state))
        return np.concatenate(xs), np.concatenate(ys)

    def evaluate(self, encoder: Encoder, dataset: MultiViewDataset, workdir: Path | None = None) -> TaskResult:
        x_train, y_train = self.features(encoder, dataset, "train")
        x_test, y_test = self.features(encoder, dataset, "test")
        regressor = probe_regressor(self.probe, self.seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            regressor.fit(x_train, y_train)
        mse = mean_squared_error(y_test, regressor.predict(x_test), multioutput="raw_values")
        metrics: dict[str, float | None] = summarize(dict(zip(TARGETS, mse, strict=True)))
        metrics.update({f"var_{k}": float(v) for k, v in zip(TARGETS, y_test.var(axis=0), strict=True)})
        metrics.update({"train_frames": float(len(x_train)), "test_frames": float(len(x_test)),
                        "probe_epochs": float(regressor[-1].n_iter_)})
        notes = [f"MSE on the simulator's scale (x in m, velocities in m/s and rad/s); {len(x_train)} train "
                 f"and {len(x_test)} test frames from camera {self.probe.camera!r}."]
        return TaskResult(metrics, notes)

    def table(self, metrics: Mapping[str, Any]) -> list[dict[str, Any]]:
        rows = [{"attribute": k, "MSE": metrics[f"mse_{k}"], "test variance": metrics[f"var_{k}"]}
                for k in TARGETS]
        rows += [{"attribute": name.capitalize(), "MSE": metrics[name], "test variance": None}
                 for name in ("position", "motion", "average")]
        return rows
