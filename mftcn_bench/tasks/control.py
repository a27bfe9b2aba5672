"""Control tasks: PPO on a frozen encoder's embedding (swingup, swingup-160, swingup-moving, cheetah).

The encoder is trained on the task's multi-view dataset (cartpole: random actions from random initial
states, the same data as cartpole-probe, so a trained encoder is shared; cheetah: rollouts of an expert
PPO policy trained on true state). A policy then learns from the embedding of one camera's frames only,
with PPO (`mftcn_bench.rl.ppo`), and is tested on `eval_episodes` episodes of the full 1000 simulator
steps with its mean action: the result is the mean and standard deviation of those returns, on the
suite's 1000-step scale whatever the action repeat. The learning curve (training return against frames
and wall time) is stored with the result (the runner draws it to `curve.png` in the run's folder).

pixels-cnn is the exception that proves the rule: its CNN has no training signal of its own and is
trained by the PPO losses together with the policy (the environment emits raw clips for it).

swingup-probe-state (`ProbeStateControlTask`) is an analysis of what limits PPO on an embedding: the
policy sees the cartpole state that the cartpole-probe's MLP, fitted on the task's dataset, predicts from
[e_t, e_t - e_{t-1}], so its return bounds what the embedding's information about the state allows once
the mapping to state is given rather than learnt by PPO. It reads its dataset itself, so unlike the other
control tasks it is no `tasks.base.OnlineTask`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sklearn.metrics import r2_score
from torch import nn
from torchrl.envs import TransformedEnv

from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.home import BenchHome
from mftcn_bench.core.progress import progress_bar
from mftcn_bench.core.specs import parse_table
from mftcn_bench.data.cartpole import TARGETS, collect_episode
from mftcn_bench.data.dataset import Collector, MultiViewDataset
from mftcn_bench.encoders.base import Encoder, trains_with_policy, uses_pixels
from mftcn_bench.rl.demos import demo_collector, recorded_config
from mftcn_bench.rl.expert import ExpertSetup
from mftcn_bench.rl.observation import PixelClip, Readout, observed_env
from mftcn_bench.rl.observers import make_observer
from mftcn_bench.rl.ppo import PPOConfig, evaluate_policy, train_ppo
from mftcn_bench.rl.suite_env import EnvFactory, SuiteConfig
from mftcn_bench.sim.rendering import RenderSettings
from mftcn_bench.sim.suite_limits import check_dataset_fits, check_episode_fits
from mftcn_bench.tasks.base import TaskResult
from mftcn_bench.tasks.probe import ProbeConfig, ProbeMLP, fit_probe, probe_split


class ClipTrunk(nn.Module):
    """A clip network (uint8 [B, n, 3, H, W] -> [B, D]) applied over any leading batch dimensions."""

    def __init__(self, net: nn.Module, out_features: int) -> None:
        super().__init__()
        # channels-last convolutions: a pixels-cnn PPO minibatch on one core 0.50 -> 0.37 s (docs/PERFORMANCE.md)
        self.net, self.out_features = net.to(memory_format=torch.channels_last), out_features

    def forward(self, clips: torch.Tensor) -> torch.Tensor:
        lead = clips.shape[:-4]
        out = self.net(clips.reshape(-1, *clips.shape[-4:]))
        return out.reshape(*lead, out.shape[-1])


def _table(cls, task: str, name: str, table: Mapping[str, Any]):
    return parse_table(cls, f"task {task!r}", name, table)


class PPOTask:
    """What the control tasks share: the environment and PPO settings of the spec, PPO on the (read-out)
    embedding of one camera, and the test episodes; metrics: return mean and std over them."""

    def __init__(self, config: Mapping[str, Any], seed: int) -> None:
        self.config, self.seed = config, seed
        self.device = torch.device("cpu")
        self._bars = True  # PPO's progress bar where tqdm shows one (a terminal), unless --no-progress
        dataset = config["dataset"]
        seen_as = {"height": dataset["height"], "width": dataset["width"], "frame_every": self.data_frame_every(),
                   "render": RenderSettings.from_table(f"task {config['name']!r}", dataset["render"])}
        self.env_config = _table(SuiteConfig, config["name"], "env", {**config["env"], **seen_as})
        self.ppo = _table(PPOConfig, config["name"], "ppo", config["ppo"])
        env = self.env_config
        check_episode_fits(env.domain, env.task, env.episode_length, f"task {config['name']!r}: [env] episode_length")
        check_dataset_fits(env.domain, env.task, dataset, f"task {config['name']!r}: [dataset]")
        if self.env_config.camera not in dataset["cameras"]:
            raise SpecError(f"task {config['name']!r}: [env] camera {self.env_config.camera!r} is not one of the "
                            f"dataset's cameras {', '.join(dataset['cameras'])}")

    def show_progress(self, enabled: bool) -> None:
        """PPO's progress bar: off with `--no-progress` (`tasks.base.ShowsProgress`)."""
        self._bars = enabled

    def data_frame_every(self) -> int:
        """Physics steps between two frames of the task's data set: its `action_repeat` (the collector steps
        that many times per frame), so the rollouts' stream has the frame rate the encoder learnt from."""
        return int(self.config["dataset"]["action_repeat"])

    def to_device(self, device: torch.device) -> None:
        """PPO's networks, losses and GAE run on `device` (`core.device.DevicePlaced`); environments and
        rendering stay on the CPU. (The cheetah expert trains on the CPU whatever the device: a 2x256 MLP
        on state gains nothing from a GPU, and its demonstrations then key one dataset for every device.)"""
        self.device = torch.device(device)

    @property
    def dataset_config(self) -> Mapping[str, Any]:
        return self.config["dataset"]

    @property
    def collector(self) -> Collector:
        return collect_episode

    def env_factory(self, encoder: Encoder, readout: Readout | None = None) -> tuple[EnvFactory, nn.Module | None]:
        """The environments this task trains and tests `encoder`'s policy on (the encoder's observation in
        them; a trunk on raw clips for an encoder trained with the policy), and that trunk or None."""
        info = encoder.info
        joint = trains_with_policy(encoder)

        def make_env(num_envs: int, seed: int) -> TransformedEnv:
            if joint:
                return observed_env(self.env_config, num_envs, seed, None, info.embedding_dim, True,
                                    pixel_clip=PixelClip(info.frames, info.stride))
            return observed_env(self.env_config, num_envs, seed, make_observer(encoder, num_envs),
                                info.embedding_dim, uses_pixels(encoder), lookback=info.lookback, readout=readout)

        trunk = ClipTrunk(encoder.net, info.embedding_dim) if joint else None
        return make_env, trunk

    def _train_and_test(self, encoder: Encoder, workdir: Path, readout: Readout | None = None) -> TaskResult:
        """PPO on the embedding (mapped by `readout` when given), then the test episodes."""
        make_env, trunk = self.env_factory(encoder, readout)
        with progress_bar(f"ppo {self.config['name']}", "batch", self._bars) as progress:
            nets, state = train_ppo(make_env, self.ppo, self.seed, workdir, progress, trunk, self.device)
        returns = evaluate_policy(make_env, nets, self.ppo.eval_episodes,
                                  min(self.ppo.num_envs, self.ppo.eval_episodes), self.seed, self.device)
        curves = {"train": {"frames": state.curve_frames, "wall_s": state.curve_wall_s,
                            "return": state.curve_return},
                  # a run resumed from a checkpoint older than the diagnostics has them for part of its batches
                  "ppo": {"frames": state.curve_frames, **{name: column for name, column in state.diagnostics.items()
                                                           if len(column) == len(state.curve_frames)}},
                  "test": {"episode": [float(i) for i in range(len(returns))], "return": returns.tolist()}}
        # Over the test episodes, as the seeds' std: the sample std (ddof=1).
        metrics = {"return_mean": float(returns.mean()), "return_std": float(returns.std(ddof=1)),
                   "episodes": float(len(returns)), "frames": float(state.frames),
                   "train_wall_s": float(state.wall_s),
                   "train_fps": float(state.frames / state.wall_s) if state.wall_s else None}
        notes = [f"PPO: {state.frames:,} frames in {state.wall_s / 60:.1f} min "
                 f"(action repeat {self.env_config.action_repeat}, {self.ppo.num_envs} environments); "
                 f"test: {len(returns)} episodes of {self.env_config.episode_length} steps, mean action"]
        return TaskResult(metrics, notes, curves)

    def table(self, metrics: Mapping[str, Any]) -> list[dict[str, Any]]:
        return [{"return (mean)": metrics["return_mean"], "return (sample std, ddof=1)": metrics["return_std"],
                 "test episodes": int(metrics["episodes"]), "training frames": int(metrics["frames"])}]


class ControlTask(PPOTask):
    """PPO on the frozen embedding of one camera. The dataset only trains the encoder (`OnlineTask`)."""

    def evaluate(self, encoder: Encoder, dataset: MultiViewDataset, workdir: Path) -> TaskResult:
        return self.evaluate_online(encoder, workdir)

    def evaluate_online(self, encoder: Encoder, workdir: Path) -> TaskResult:
        return self._train_and_test(encoder, workdir)


@dataclass(frozen=True)
class ProbeReadout:
    """The fitted probe as a `Readout`: [e_t, e_t - e_{t-1}] -> the predicted state in TARGETS order, the
    order and scale in which the true-state encoder gives the state."""

    regressor: ProbeMLP
    out_features: int = len(TARGETS)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        return self.regressor.predict(observation)


class ProbeStateControlTask(PPOTask):
    """PPO on the cartpole state that the probe (`[probe]`, cartpole-probe's MLP) predicts from the
    embedding; the probe is fitted on the train split of the task's dataset before PPO and its R^2 on the
    test split is stored with the return."""

    def __init__(self, config: Mapping[str, Any], seed: int) -> None:
        super().__init__(config, seed)
        name = config["name"]
        self.probe = _table(ProbeConfig, name, "probe", config["probe"])
        if self.env_config.domain != "cartpole":
            raise SpecError(f"task {name!r}: the probe regresses the cartpole's state; [env] domain is "
                            f"{self.env_config.domain!r}")
        if not self.env_config.embedding_difference:
            raise SpecError(f"task {name!r}: the probe reads [e_t, e_t - e_t-1]; set [env] embedding_difference = true")
        if self.probe.camera != self.env_config.camera:
            raise SpecError(f"task {name!r}: [probe] camera {self.probe.camera!r} must be the policy's camera, "
                            f"[env] camera {self.env_config.camera!r}")

    def evaluate(self, encoder: Encoder, dataset: MultiViewDataset, workdir: Path) -> TaskResult:
        x_train, y_train, episodes = probe_split(encoder, dataset, self.probe.camera, "train")
        regressor = fit_probe(self.probe, self.seed, x_train, y_train, episodes)
        x_test, y_test, _ = probe_split(encoder, dataset, self.probe.camera, "test")
        r2 = r2_score(y_test, regressor.predict(x_test), multioutput="raw_values")
        result = self._train_and_test(encoder, workdir, ProbeReadout(regressor))
        quality = {f"probe_r2_{k}": float(v) for k, v in zip(TARGETS, r2, strict=True)}
        quality["probe_r2_mean"] = float(r2.mean())
        note = (f"policy input: the probe's prediction of the state from [e_t, e_t - e_t-1] (fitted on "
                f"{len(x_train)} train frames; test R^2 " + ", ".join(f"{k} {v:.2f}" for k, v in
                                                                     zip(TARGETS, r2, strict=True)) + ")")
        return TaskResult({**result.metrics, **quality}, [*result.notes, note], result.curves)

    def table(self, metrics: Mapping[str, Any]) -> list[dict[str, Any]]:
        return [{**row, "probe R^2 (mean of 5)": metrics.get("probe_r2_mean")} for row in super().table(metrics)]


class ExpertDemoControlTask(ControlTask):
    """A control task whose encoder learns from an expert's demonstrations only (cheetah).

    The expert (PPO on true state, `[expert_ppo]`) is the project's pinned file for this config, or trained
    once and cached under the home's `experts/` (`rl.expert`); the dataset records its episodes from every
    camera of `[dataset]`.
    """

    def __init__(self, config: Mapping[str, Any], seed: int) -> None:
        super().__init__(config, seed)
        expert_ppo = _table(PPOConfig, config["name"], "expert_ppo", config["expert_ppo"])
        self.expert = ExpertSetup.of_task(self.env_config, expert_ppo, int(config["dataset"]["seed"]))  # RecordsExpert
        self._expert_path: Path | None = None

    @property
    def dataset_config(self) -> Mapping[str, Any]:
        # The expert's identity (and the pinned demonstrations') is part of the data's: another gives another dataset.
        return recorded_config(self.expert, self.config["dataset"])

    @property
    def demos_config(self) -> Mapping[str, Any]:
        """The expert's demonstrations: this task's own data set (`tasks.base.RecordsExpert`)."""
        return self.dataset_config

    def prepare_artifacts(self, home: BenchHome, show_progress: bool = True) -> None:
        """Train (or find) the expert before the dataset is collected from it."""
        self._expert_path = self.expert.ensure(home.experts, show_progress)

    @property
    def collector(self) -> Collector:
        # Before prepare_artifacts it has no expert: it keys the dataset, and refuses to collect.
        return demo_collector(self.expert, self._expert_path, self.config["dataset"])
