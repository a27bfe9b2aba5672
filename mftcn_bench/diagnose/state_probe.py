"""How much of the true state an encoder's embedding carries, camera by camera.

The encoder of `mftcn-bench run --encoder E --task T --preset P --seed S` is loaded (or fitted, when it is not
cached yet); each camera of the task's data set (or those asked for) is embedded, and the cartpole-probe's
MLP (features [e_t, e_t - e_{t-1}]; the task's own [probe] table, else cartpole-probe's) is fitted to the
simulator state (as true-state embeds it: a cartpole angle as its sine and cosine) on the train split. The
answer is R^2 per state dimension on the test split, and their mean. It tells "the embedding does not carry
the state" apart from "PPO does not learn from it" for a control row that falls short of the paper, and which
camera carries what. For a task whose data set is an expert's demonstrations (cheetah), `random_episodes`
also records that many episodes of uniformly random actions (held for the action repeat) and scores the same
probe on them: states the demonstrations never visit, like a PPO agent's early ones.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from sklearn.metrics import r2_score

from mftcn_bench.core import registry
from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.home import BenchHome
from mftcn_bench.core.specs import parse_table
from mftcn_bench.data.cartpole import TARGETS
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.diagnose.coverage import pick_cameras
from mftcn_bench.encoders.base import Encoder, embed_episode
from mftcn_bench.encoders.baselines import CARTPOLE_STATE_COLUMNS, state_embedding
from mftcn_bench.rl.demos import ExpertDemoCollector
from mftcn_bench.run.artifacts import build_encoder, prepare_dataset
from mftcn_bench.run.plan import PreparedRun, RunRequest, prepare_with_encoder
from mftcn_bench.sim.rendering import ensure_gl
from mftcn_bench.tasks.probe import ProbeConfig, ProbeMLP, fit_probe, probe_features

RANDOM_EPISODE_OFFSET = 1_000_000  # random-action episodes' indices: past any data set's, so other initial states


@dataclass(frozen=True)
class ProbeScore:
    """The probe's R^2 per state dimension on one set of frames."""

    frames: int
    r2: tuple[float, ...]

    @property
    def mean(self) -> float:
        return float(np.mean(self.r2))


@dataclass(frozen=True)
class CameraProbe:
    """One camera's probe: fitted on `train_frames` frames of the train split, scored on the test split and,
    when asked, on random-action episodes."""

    camera: str
    train_frames: int
    test: ProbeScore
    random_actions: ProbeScore | None = None


@dataclass(frozen=True)
class StateProbe:
    """`probe_cameras`' answer: what was probed, the state's dimension names and each camera's scores."""

    encoder: str
    task: str
    preset: str
    seed: int
    dimensions: tuple[str, ...]
    cameras: tuple[CameraProbe, ...]
    random_episodes: int = 0


@dataclass(frozen=True)
class FittedProbe:
    """The probe of one camera's embedding, fitted on the train split."""

    camera: str
    regressor: ProbeMLP
    train_frames: int


def dimension_names(state_columns: int) -> tuple[str, ...]:
    """Names of the probe's targets for a state of `state_columns` columns (`state_embedding`'s mapping)."""
    if state_columns == CARTPOLE_STATE_COLUMNS:
        return TARGETS
    return tuple(f"state[{i}]" for i in range(state_columns))


def probe_config(prepared: PreparedRun) -> ProbeConfig:
    """The task's own [probe] table (its preset and overrides applied), else cartpole-probe's."""
    task = prepared.config["task"]
    if "probe" in task:
        return parse_table(ProbeConfig, f"task {prepared.request.task!r}", "probe", task["probe"])
    return parse_table(ProbeConfig, "task 'cartpole-probe'", "probe",
                       registry.get("tasks", "cartpole-probe").spec.tables["probe"])


def features(encoder: Encoder, episodes: Iterable[tuple[np.ndarray, np.ndarray]]
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Probe features, state targets and episode numbers of every frame of (frames of one view [T, H, W, 3],
    states [T, S]) episodes."""
    xs, ys, names = [], [], []
    for number, (frames, state) in enumerate(episodes):
        xs.append(probe_features(embed_episode(encoder, frames, state)))
        ys.append(state_embedding(state))
        names.append(np.full(len(state), number))
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(names)


def split_episodes(dataset: MultiViewDataset, camera: str, split: str) -> Iterable[tuple[np.ndarray, np.ndarray]]:
    """(frames of `camera`, states) of every episode of one split."""
    view = dataset.cameras.index(camera)
    return ((episode.frames[view], episode.state) for episode in dataset.iter_episodes(split))


def fit_camera_probe(encoder: Encoder, dataset: MultiViewDataset, camera: str, probe: ProbeConfig,
                     seed: int) -> FittedProbe:
    """The probe of `camera`'s embedding, fitted on the train split (early stopping on whole episodes)."""
    x, y, episodes = features(encoder, split_episodes(dataset, camera, "train"))
    with warnings.catch_warnings():
        # a smoke preset's train split is smaller than the probe's batch; sklearn clips the batch to it, once
        # an epoch, and says so each time
        warnings.filterwarnings("ignore", message="Got `batch_size` less than 1 or larger than sample size")
        return FittedProbe(camera, fit_probe(probe, seed, x, y, episodes), len(x))


def score(fitted: FittedProbe, encoder: Encoder, episodes: Iterable[tuple[np.ndarray, np.ndarray]]) -> ProbeScore:
    """R^2 per state dimension of `fitted` on (frames of its camera, states) episodes."""
    x, y, _ = features(encoder, episodes)
    r2 = r2_score(y, fitted.regressor.predict(x), multioutput="raw_values")
    return ProbeScore(len(x), tuple(float(v) for v in r2))


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
        raise SpecError(f"--random-episodes needs a task whose dataset is an expert's demonstrations (cheetah); "
                        f"{prepared.request.task!r}'s is not")
    ensure_gl()  # before dm_control is imported: it picks its OpenGL back end then
    from dm_control import suite

    dim = suite.load(prepared.task.dataset_config["domain"], demos.env_config.task).action_spec().shape[0]
    return ExpertDemoCollector(demos.expert_path, demos.env_config, demos.ppo,
                               policy=UniformPolicy(dim, prepared.request.seed))


def probe_cameras(request: RunRequest, home: BenchHome, cameras: Sequence[str] | None = None,
                  random_episodes: int = 0, show_progress: bool = False) -> StateProbe:
    """The state probe of `request`'s encoder on each of `cameras` (default every camera of the task's data
    set): R^2 per state dimension on the test split and, with `random_episodes`, on that many random-action
    episodes. Names, cameras and counts are checked before any data is collected or encoder fitted."""
    if random_episodes < 0:
        raise SpecError(f"--random-episodes must be >= 0, got {random_episodes}")
    # The probe reads the task's data whatever the encoder (a run of true state on swing-up reads none).
    planned, untrained = prepare_with_encoder(request)
    prepared = replace(planned, reads_data=True)
    dataset_config: Any = prepared.task.dataset_config
    picked = pick_cameras(list(dataset_config["cameras"]), cameras)
    randomised = random_action_collector(prepared) if random_episodes else None
    probe = probe_config(prepared)
    dataset = prepare_dataset(prepared, home, show_progress=show_progress)
    encoder, _ = build_encoder(prepared, dataset, home, show_progress=show_progress, untrained=untrained)
    # Recorded once, from every camera of the data set: each camera's probe reads its own view of them.
    recorded = [] if randomised is None else [randomised(dataset.config, RANDOM_EPISODE_OFFSET + i)
                                              for i in range(random_episodes)]
    results = []
    for camera in picked:
        fitted = fit_camera_probe(encoder, dataset, camera, probe, request.seed)
        view = dataset.cameras.index(camera)
        test = score(fitted, encoder, split_episodes(dataset, camera, "test"))
        random_actions = (score(fitted, encoder, ((e["frames"][view], e["state"]) for e in recorded))
                          if recorded else None)
        results.append(CameraProbe(camera, fitted.train_frames, test, random_actions))
    state_columns = dataset.load(dataset.episodes("train")[0]).state.shape[1]
    return StateProbe(request.encoder, request.task, prepared.preset, request.seed, dimension_names(state_columns),
                      tuple(results), random_episodes)
