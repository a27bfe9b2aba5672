"""Imitation (imitate-swingup, imitate-cheetah): behaviour cloning on the frozen embedding, from an expert's
demonstrations, the cheap control readout of frozen-encoder suites (CortexBench, R3M, VIP, MVP).

The expert is PPO on the true state (`[expert_ppo]`; the pinned file or trained in the home, `rl.expert`). Its
demonstrations (`[demos]`) are its episodes filmed by the policy's camera at the encoder's stream (the size,
render settings and frame rate of the task's `[dataset]`), with the true state and the expert's action at each
frame; they are recorded once and keyed like any data set, so every encoder clones the same episodes. With
`[demos] action_noise` the expert is pushed off its path by noise while it records (DART, `rl.demos`). The task's
`[dataset]` is the encoder's training data, the matching PPO task's, so a trained encoder is shared with it.

The readout (`[bc]`): the embedding of each demonstration frame (with `[env] embedding_difference`,
[e_t, e_t - e_{t-1}]), the actions the expert took there, and an MLP fitted to them by mean-squared error
(the probe's sklearn MLP: standardised inputs, Adam) on the first `demonstrations` episodes for a fixed
number of gradient steps, whatever their count, so that rows of 5, 25 and 100 demonstrations differ only in
data. The clone then acts online in the harness's own environments (`observed_env`: the stream a PPO policy
sees) for `eval_episodes` episodes seeded apart from the demonstrations; the expert acts from the same initial
states (the same environment seed), so `fraction_of_expert` compares like with like.

pixels-cnn is refused: its CNN is trained with a policy, and here there is none to train it with.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from sklearn.exceptions import DataConversionWarning
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from mftcn_bench.core.errors import DataError, SpecError
from mftcn_bench.core.home import BenchHome
from mftcn_bench.core.specs import parse_table
from mftcn_bench.data.cartpole import collect_episode
from mftcn_bench.data.dataset import Collector, MultiViewDataset, ensure_dataset
from mftcn_bench.encoders.base import Encoder, embed_episode, trains_with_policy, uses_pixels
from mftcn_bench.rl.demos import StatePolicy, demo_collector, recorded_config
from mftcn_bench.rl.expert import ExpertSetup
from mftcn_bench.rl.observation import observed_env
from mftcn_bench.rl.observers import make_observer
from mftcn_bench.rl.ppo import EVAL_SEED_OFFSET, PPOConfig
from mftcn_bench.rl.rollout import rollout_returns
from mftcn_bench.rl.suite_env import SuiteBatchEnv, SuiteConfig
from mftcn_bench.sim.rendering import RenderSettings
from mftcn_bench.sim.suite_limits import check_dataset_fits, check_episode_fits
from mftcn_bench.tasks.base import TaskResult
from mftcn_bench.tasks.probe import ProbeConfig, fit_probe, probe_features


@dataclass(frozen=True)
class DemosConfig:
    """The `[demos]` table: which expert episodes are recorded (the camera set, size and rate are the
    encoder's data set's)."""

    name: str
    cameras: list[str]
    episodes: int          # recorded for training: the most a run may clone from
    test_episodes: int     # recorded and held out: the clone's action error on unseen demonstrations
    episode_length: int    # frames
    seed: int              # the demonstrations' initial states (apart from the encoder data's and the test's)
    expert_seed: int       # the expert's PPO seed
    action_noise: float    # std of the noise added to the expert's actions while recording (DART; `rl.demos`)

    def __post_init__(self) -> None:
        if self.episodes < 1 or self.test_episodes < 1 or self.episode_length < 1:
            raise SpecError(f"task.demos: episodes, test_episodes and episode_length must be >= 1, got "
                            f"{self.episodes}, {self.test_episodes} and {self.episode_length}")
        if not (math.isfinite(self.action_noise) and self.action_noise >= 0):
            raise SpecError(f"task.demos.action_noise must be a number >= 0 (0: the expert's own actions), got "
                            f"{self.action_noise}")


@dataclass(frozen=True)
class BCConfig:
    """The `[bc]` table: the clone's MLP, its training budget and its test."""

    demonstrations: int    # the first this many recorded episodes are cloned
    hidden: list[int]
    lr: float
    steps: int             # Adam steps, whatever the number of demonstrations
    batch_size: int
    eval_episodes: int
    eval_envs: int         # environments stepped together in the test

    def __post_init__(self) -> None:
        rules = {"demonstrations": self.demonstrations >= 1, "steps": self.steps >= 1,
                 "batch_size": self.batch_size >= 1, "eval_episodes": self.eval_episodes >= 1,
                 "eval_envs": self.eval_envs >= 1, "lr": self.lr > 0,
                 "hidden": bool(self.hidden) and all(h >= 1 for h in self.hidden)}
        for key, ok in rules.items():
            if not ok:
                allowed = "a non-empty list of sizes >= 1" if key == "hidden" else "> 0" if key == "lr" else ">= 1"
                raise SpecError(f"task.bc.{key} must be {allowed}, got {getattr(self, key)}")


def demo_rows(encoder: Encoder, dataset: MultiViewDataset, camera: str, split: str, count: int | None,
              difference: bool, frames_per_step: int) -> tuple[np.ndarray, np.ndarray]:
    """What the clone learns from: per agent step of the first `count` episodes of `split` (all when None),
    the observation a rollout gives the policy (the embedding of `camera`'s clip, with `difference`
    [e_t, e_t - e_{t-1}] over the stream) and the expert's action then. With several stream frames per
    agent step the expert decided at every `frames_per_step`-th frame, where the rollout observes."""
    view = dataset.cameras.index(camera)
    xs, ys = [], []
    for index in dataset.episodes(split)[:count]:
        episode = dataset.load(index)
        embeddings = embed_episode(encoder, episode.frames[view], episode.state)
        observed = probe_features(embeddings) if difference else embeddings
        xs.append(observed[::frames_per_step])
        ys.append(episode.action[::frames_per_step])
    return np.concatenate(xs), np.concatenate(ys).astype(np.float64)


class ImitationTask:
    """Behaviour cloning on a frozen embedding; the encoder trains on the task's `[dataset]` (random-action
    videos, `collect_episode`, as the matching PPO task's), the clone on the expert's `[demos]`."""

    def __init__(self, config: Mapping[str, Any], seed: int) -> None:
        self.config, self.seed = config, seed
        name, dataset = config["name"], config["dataset"]
        self._bars = True
        owner = f"task {name!r}"
        seen_as = {"height": dataset["height"], "width": dataset["width"], "frame_every": int(dataset["action_repeat"]),
                   "render": RenderSettings.from_table(owner, dataset["render"])}
        self.env_config = parse_table(SuiteConfig, owner, "env", {**config["env"], **seen_as})
        self.demos = parse_table(DemosConfig, owner, "demos", config["demos"])
        self.expert = ExpertSetup.of_task(self.env_config, parse_table(PPOConfig, owner, "expert_ppo",
                                                                       config["expert_ppo"]),
                                          self.demos.expert_seed)  # tasks.base.RecordsExpert
        self.bc = parse_table(BCConfig, owner, "bc", config["bc"])
        env = self.env_config
        check_episode_fits(env.domain, env.task, env.episode_length, f"{owner}: [env] episode_length")
        check_dataset_fits(env.domain, env.task, dataset, f"{owner}: [dataset]")
        check_dataset_fits(env.domain, env.task, self.demos_config, f"{owner}: [demos]")
        if env.camera not in self.demos.cameras:
            raise SpecError(f"{owner}: [demos] cameras {self.demos.cameras} must hold the policy's camera, [env] "
                            f"camera {env.camera!r}")
        if self.bc.demonstrations > self.demos.episodes:
            raise SpecError(f"{owner}: task.bc.demonstrations ({self.bc.demonstrations}) is more than the "
                            f"demonstrations recorded, task.demos.episodes ({self.demos.episodes}); use at most "
                            f"{self.demos.episodes} or record more")
        self._expert_path: Path | None = None
        self._demos: MultiViewDataset | None = None

    # -- the encoder's data (the matching PPO task's, so its trained encoder is shared) --------------------
    @property
    def dataset_config(self) -> Mapping[str, Any]:
        return self.config["dataset"]

    @property
    def collector(self) -> Collector:
        return collect_episode

    # -- the expert and its demonstrations --------------------------------------------------------------
    @property
    def demos_config(self) -> dict[str, Any]:
        """The demonstrations' data set: the expert's episodes at the encoder data's size, render settings
        and frame rate, keyed by the expert and its pinned demonstrations, if any (`rl.demos.recorded_config`)."""
        data, demos = self.config["dataset"], self.demos
        # The noise enters only when there is some, so noiseless demonstrations keep the id of the expert data
        # set they are (cheetah's: the encoder's own data).
        noise = {"action_noise": demos.action_noise} if demos.action_noise else {}
        return recorded_config(self.expert, {
            "name": demos.name, "domain": self.env_config.domain, "cameras": list(demos.cameras),
            "height": data["height"], "width": data["width"], "train_episodes": demos.episodes,
            "test_episodes": demos.test_episodes, "episode_length": demos.episode_length,
            "action_repeat": data["action_repeat"], "seed": demos.seed, "render": data["render"], **noise})

    def show_progress(self, enabled: bool) -> None:
        """The expert's PPO bar and the demonstrations' collection bar (`tasks.base.ShowsProgress`)."""
        self._bars = enabled

    def check_encoder(self, encoder: Encoder) -> None:
        """Refuse an encoder with nothing to clone from: one trained with a policy (`tasks.base.ChecksEncoder`)."""
        if trains_with_policy(encoder):
            raise SpecError(f"task {self.config['name']!r} clones an expert on a frozen embedding; encoder "
                            f"{encoder.info.name!r} is trained with a policy (nothing to clone from): use an "
                            f"encoder that embeds frames, true-state or random-state")

    def expert_policy(self) -> StatePolicy:
        """The expert's mean action for one simulator state (what the demonstrations recorded)."""
        if self._expert_path is None:
            raise RuntimeError("the expert must be trained (prepare_artifacts) before it acts")
        return self.expert.policy(self._expert_path)

    def prepare_artifacts(self, home: BenchHome, show_progress: bool = True) -> None:
        """Train (or find) the expert, then record (or find) its demonstrations (`tasks.base.NeedsArtifacts`)."""
        if self._expert_path is None:
            self._expert_path = self.expert.ensure(home.experts, show_progress)
        config = self.demos_config
        collector = demo_collector(self.expert, self._expert_path, config, policy=self.expert_policy())
        self._demos = ensure_dataset(home.datasets, config, collector, show_progress=show_progress)

    # -- the clone --------------------------------------------------------------------------------------
    def _regressor_config(self, rows: int) -> ProbeConfig:
        """The probe's MLP as the clone: `bc.steps` Adam steps as whole epochs over `rows` rows, plain action
        MSE (targets not standardised), no early stopping (a fixed budget for every row of a table)."""
        per_epoch = math.ceil(rows / min(self.bc.batch_size, rows))
        return ProbeConfig(camera=self.env_config.camera, hidden=list(self.bc.hidden), lr=self.bc.lr,
                           epochs=max(1, math.ceil(self.bc.steps / per_epoch)), batch_size=self.bc.batch_size,
                           tol=0.0, early_stopping=False, validation_fraction=0.0, patience=1,
                           standardize_targets=False)

    def evaluate(self, encoder: Encoder, dataset: MultiViewDataset, workdir: Path) -> TaskResult:
        self.check_encoder(encoder)
        if self._demos is None:
            raise RuntimeError("the demonstrations must be recorded (prepare_artifacts) before the clone learns")
        recorded = len(self._demos.episodes("train"))
        if self.bc.demonstrations > recorded:
            raise DataError(f"task.bc.demonstrations ({self.bc.demonstrations}) is more than the {recorded} "
                            f"demonstrations recorded in {self._demos.root}")
        env, camera = self.env_config, self.env_config.camera
        rows = {split: demo_rows(encoder, self._demos, camera, split,
                                 self.bc.demonstrations if split == "train" else None,
                                 env.embedding_difference, env.frames_per_step) for split in ("train", "test")}
        x, y = rows["train"]
        config = self._regressor_config(len(x))
        with warnings.catch_warnings():  # one action column is sklearn's multi-output form, which it warns of
            warnings.simplefilter("ignore", DataConversionWarning)
            clone = fit_probe(config, self.seed, x, y, np.zeros(len(x), dtype=int))
        train_mse = float(np.mean((clone.predict(x) - y) ** 2))
        test_mse = float(np.mean((clone.predict(rows["test"][0]) - rows["test"][1]) ** 2))

        n = min(self.bc.eval_envs, self.bc.eval_episodes)
        test_seed = self.seed + EVAL_SEED_OFFSET  # apart from training's seeds, as PPO's test episodes
        info = encoder.info

        def clone_env() -> EnvBase:
            return observed_env(env, n, test_seed, make_observer(encoder, n), info.embedding_dim, uses_pixels(encoder),
                                lookback=info.lookback)

        def clone_act(td: TensorDictBase) -> np.ndarray:
            return clone.predict(td.get("observation").numpy().astype(np.float64))

        expert = self.expert_policy()

        def expert_act(td: TensorDictBase) -> np.ndarray:
            return np.stack([expert.act(state) for state in td.get("state")[:, -1].numpy()])

        returns = rollout_returns(clone_env, clone_act, self.bc.eval_episodes)
        expert_returns = rollout_returns(lambda: SuiteBatchEnv(self.expert.env, n, test_seed), expert_act,
                                         self.bc.eval_episodes)
        expert_mean = float(expert_returns.mean())
        metrics: dict[str, float | None] = {
            "return_mean": float(returns.mean()), "return_std": float(returns.std(ddof=1)) if len(returns) > 1 else 0.0,
            "expert_return_mean": expert_mean,
            "expert_return_std": float(expert_returns.std(ddof=1)) if len(expert_returns) > 1 else 0.0,
            "fraction_of_expert": float(returns.mean()) / expert_mean if expert_mean > 0 else None,
            "demonstrations": float(self.bc.demonstrations), "episodes": float(len(returns)),
            "bc_train_mse": train_mse, "bc_heldout_mse": test_mse, "bc_train_rows": float(len(x)),
            "bc_epochs": float(clone.n_iter_)}
        curves = {"test": {"episode": [float(i) for i in range(len(returns))], "return": returns.tolist(),
                           "expert_return": expert_returns.tolist()}}
        view = "[e_t, e_t - e_t-1]" if env.embedding_difference else "e_t"
        notes = [f"behaviour cloning: an MLP {list(self.bc.hidden)} on {view} of camera {camera!r}, fitted to the "
                 f"expert's actions in {self.bc.demonstrations} demonstrations ({len(x)} agent steps, "
                 f"{clone.n_iter_} epochs, about {self.bc.steps} Adam steps); demonstrations data set "
                 f"{self._demos.root.name} (fingerprint {self._demos.fingerprint[:12]})",
                 f"test: {len(returns)} episodes of {env.episode_length} steps from initial states seeded apart "
                 f"from the demonstrations; the expert from the same initial states: {expert_mean:.1f}"]
        return TaskResult(metrics, notes, curves)

    def table(self, metrics: Mapping[str, Any]) -> list[dict[str, Any]]:
        return [{"return (mean)": metrics["return_mean"], "return (sample std, ddof=1)": metrics["return_std"],
                 "expert return": metrics["expert_return_mean"], "fraction of expert": metrics["fraction_of_expert"],
                 "demonstrations": int(metrics["demonstrations"]), "BC train MSE": metrics["bc_train_mse"],
                 "BC held-out MSE": metrics.get("bc_heldout_mse")}]


class ExpertDataImitationTask(ImitationTask):
    """Imitation where the encoder, too, learns from the expert's demonstrations only (cheetah): the task's
    `[dataset]` is the cheetah task's, recorded from the same expert, so the trained encoder is shared."""

    def __init__(self, config: Mapping[str, Any], seed: int) -> None:
        super().__init__(config, seed)
        if int(config["dataset"]["seed"]) != self.demos.expert_seed:
            raise SpecError(f"task {config['name']!r}: task.demos.expert_seed ({self.demos.expert_seed}) must be "
                            f"the [dataset] seed ({config['dataset']['seed']}), the seed of the expert whose "
                            f"episodes the encoder learns from")
        if self.demos.action_noise:
            raise SpecError(f"task {config['name']!r}: task.demos.action_noise must be 0 here: the demonstrations "
                            f"are the encoder's own data, the expert's episodes as it acts (got "
                            f"{self.demos.action_noise})")

    @property
    def dataset_config(self) -> Mapping[str, Any]:
        # As `tasks.control.ExpertDemoControlTask`: the expert's identity is part of the data's.
        return recorded_config(self.expert, self.config["dataset"])

    @property
    def collector(self) -> Collector:
        # Before prepare_artifacts it has no expert: it keys the dataset, and refuses to collect.
        return demo_collector(self.expert, self._expert_path, self.config["dataset"])
