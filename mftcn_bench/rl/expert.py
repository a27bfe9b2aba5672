"""Expert policies for demonstration datasets: PPO on true state, pinned in the project or trained once.

The cheetah task's encoder only ever sees an expert at work (the paper's protocol). The expert is a PPO
policy trained on the simulator state with the task's `[expert_ppo]` settings. The project ships the experts
of its presets as committed files (`experts/` at the root, `mftcn_bench/specs/experts` in the package): the
weights `<domain>-<task>-<config key>.pt` and a sidecar `.json` with their sha256 and what trained them (the
config key hashes the environment as the state sees it, the PPO settings and the seed: not the code, so a
refactor keeps the file). A pinned expert is loaded, never trained, and a data set recorded from it names
the file's checksum, so every machine records its demonstrations from the same weights. An expert config
with no pinned file (a smoke preset's toy expert, an override) is trained in the home's `experts/<key>/`
(key: that config and the code), under a lock so concurrent runs train it once, resumed after a kill.
`pin_expert` (`mftcn-bench expert train`) makes a pinned file on purpose. `ExpertSetup` is the one way the
tasks recorded from an expert (cheetah's, imitation's) name, find and run theirs.
"""

from __future__ import annotations

import importlib.resources
import io
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from mftcn_bench.core import identity
from mftcn_bench.core.errors import TrainingError
from mftcn_bench.core.fileio import atomic_write_bytes, exclusive_lock
from mftcn_bench.core.progress import Progress, progress_bar
from mftcn_bench.core.provenance import content_hash, file_sha256, versions
from mftcn_bench.rl.observation import observed_env
from mftcn_bench.rl.observers import StateObserver
from mftcn_bench.rl.ppo import PolicyNetworks, PPOConfig, evaluate_policy, train_ppo
from mftcn_bench.rl.suite_env import SuiteBatchEnv, SuiteConfig

_FRAMES_ONLY = ("camera", "height", "width", "render", "frame_every")  # how frames are seen: an expert sees none


def expert_key(env: SuiteConfig, ppo: PPOConfig, seed: int) -> str:
    """The expert's identity: its environment as the state sees it (not the frames' camera, size, render
    settings or rate, so a change of how demonstrations are filmed keeps the expert), PPO settings, seed."""
    stepped = {k: v for k, v in asdict(env).items() if k not in _FRAMES_ONLY}
    return identity.expert_key(stepped, asdict(ppo), seed)


def expert_config_key(env: SuiteConfig, ppo: PPOConfig, seed: int) -> str:
    """What trains an expert, without the code: the name of its pinned file."""
    stepped = {k: v for k, v in asdict(env).items() if k not in _FRAMES_ONLY}
    return content_hash({"env": stepped, "ppo": asdict(ppo), "seed": seed})


def pinned_folder() -> Path:
    """Where the project's pinned experts are (the package's `specs/experts`, the root's `experts/`)."""
    return Path(str(importlib.resources.files("mftcn_bench") / "specs" / "experts"))


def pinned_path(env: SuiteConfig, ppo: PPOConfig, seed: int, folder: Path | None = None) -> Path:
    """The file a pinned expert of this config has (whether or not it exists)."""
    return (folder or pinned_folder()) / f"{env.domain}-{env.task}-{expert_config_key(env, ppo, seed)}.pt"


def pinned_expert(env: SuiteConfig, ppo: PPOConfig, seed: int, folder: Path | None = None) -> Path | None:
    """The pinned expert of this config, its checksum checked against its sidecar (a truncated file or a
    Git LFS pointer is refused in one line); None when the project pins none."""
    path = pinned_path(env, ppo, seed, folder)
    return checked_pinned(path, "pinned expert", "mftcn-bench expert train") if path.exists() else None


def checked_pinned(path: Path, what: str, remake: str) -> Path:
    """`path`, a committed artifact, once its checksum matches its `.json` sidecar's `sha256`; otherwise
    one line naming the file and `remake`, the command that makes it again."""
    sidecar = path.with_suffix(".json")
    try:
        expected = json.loads(sidecar.read_text())["sha256"]
    except (OSError, ValueError, KeyError):
        raise TrainingError(f"{what} {path.name} has no readable {sidecar.name} (its checksum); restore both "
                            f"files from the repository, or remake them with `{remake}`") from None
    if file_sha256(path) != expected:
        raise TrainingError(f"{what} {path} does not match the checksum in {sidecar.name}; restore it from the "
                            f"repository (a Git LFS pointer?) or remake it with `{remake} --force`")
    return path


def expert_identity(env: SuiteConfig, ppo: PPOConfig, seed: int) -> str:
    """What a data set recorded from this config's expert names: the pinned file's checksum, or (an expert
    trained in the home) the training key, which holds the code."""
    path = pinned_expert(env, ppo, seed)
    return f"pinned-{file_sha256(path)[:16]}" if path is not None else expert_key(env, ppo, seed)


def state_env_factory(env_config: SuiteConfig):
    """Environments whose observation is the simulator state (nothing rendered)."""
    sizing = SuiteBatchEnv(env_config, 1, 0)
    simulator_dim = sizing.observation_spec["state"].shape[-1]
    sizing.close()
    state_dim = int(StateObserver().push(None, np.ones(1, bool), np.zeros((1, simulator_dim))).shape[1])

    def make_env(num_envs: int, seed: int) -> TransformedEnv:
        return observed_env(env_config, num_envs, seed, StateObserver(), state_dim, False)

    return make_env


def _no_progress(done: int, total: int, stats: dict[str, float]) -> None:
    pass


def ensure_expert(experts_dir: Path, env_config: SuiteConfig, ppo: PPOConfig, seed: int,
                  progress: Progress = _no_progress) -> Path:
    """Path of the expert's weights: the pinned file when the project pins this config, else the home's
    `expert.pt`, training it first if needed."""
    pinned = pinned_expert(env_config, ppo, seed)
    return pinned if pinned is not None else train_expert(experts_dir, env_config, ppo, seed, progress)


def train_expert(experts_dir: Path, env_config: SuiteConfig, ppo: PPOConfig, seed: int,
                 progress: Progress = _no_progress) -> Path:
    """Path of the home's trained expert (`expert.pt`, its summary beside it), training it first if needed."""
    workdir = experts_dir / f"{env_config.domain}-{env_config.task}-{expert_key(env_config, ppo, seed)}"
    path = workdir / "expert.pt"
    if path.exists():
        return path
    workdir.mkdir(parents=True, exist_ok=True)
    with exclusive_lock(experts_dir / f".{workdir.name}.lock"):
        if path.exists():
            return path
        make_env = state_env_factory(env_config)
        nets, state = train_ppo(make_env, ppo, seed, workdir, progress)
        returns = evaluate_policy(make_env, nets, ppo.eval_episodes, min(ppo.num_envs, ppo.eval_episodes), seed)
        buffer = io.BytesIO()
        torch.save({"nets": nets.state_dict()}, buffer)
        summary = {"return_mean": float(returns.mean()), "return_std": float(returns.std(ddof=1)),
                   "episodes": len(returns), "frames": state.frames, "wall_s": state.wall_s,
                   "curve": {"frames": state.curve_frames, "return": state.curve_return}}
        atomic_write_bytes(workdir / "expert.json", json.dumps(summary, indent=1).encode())
        atomic_write_bytes(path, buffer.getvalue())
    return path


def pin_expert(trained: Path, env_config: SuiteConfig, ppo: PPOConfig, seed: int,
               folder: Path | None = None) -> Path:
    """Copy a home-trained expert (`train_expert`) to the pinned folder with its sidecar: the weights'
    sha256, what trained them (environment, PPO settings, seed, library versions, CPU) and its test return.
    Every data set recorded from an earlier pinned file of this config gets a new key."""
    target = pinned_path(env_config, ppo, seed, folder)
    target.parent.mkdir(parents=True, exist_ok=True)
    summary = json.loads((trained.parent / "expert.json").read_text())
    stepped = {k: v for k, v in asdict(env_config).items() if k not in _FRAMES_ONLY}
    sidecar = {"sha256": file_sha256(trained), "env": stepped, "ppo": asdict(ppo), "seed": seed,
               "return_mean": summary["return_mean"], "return_std": summary["return_std"],
               "test_episodes": summary["episodes"], "frames": summary["frames"], "versions": versions()}
    atomic_write_bytes(target, trained.read_bytes())
    atomic_write_bytes(target.with_suffix(".json"), json.dumps(sidecar, indent=1, sort_keys=True).encode())
    return target


class ExpertPolicy:
    """A trained expert's mean action for a single simulator state."""

    def __init__(self, path: Path, env_config: SuiteConfig, ppo: PPOConfig) -> None:
        from torchrl.envs import ExplorationType, set_exploration_type

        env = state_env_factory(env_config)(1, 0)
        self._nets = PolicyNetworks(env, ppo, None)
        env.close()
        try:
            self._nets.load_state_dict(torch.load(path, weights_only=True, map_location="cpu")["nets"])
        except Exception as exc:  # noqa: BLE001 - an unreadable expert gets one line
            raise TrainingError(f"expert policy {path} cannot be read ({type(exc).__name__}); delete its folder "
                                f"to train it again") from None
        self._mode = set_exploration_type(ExplorationType.DETERMINISTIC)

    @torch.no_grad()
    def act(self, state: np.ndarray) -> np.ndarray:
        """The mean action for one simulator state (as `physics_state` records it)."""
        observation = StateObserver().push(None, np.ones(1, bool), np.asarray(state, dtype=np.float64)[None])
        td = TensorDict({"observation": torch.from_numpy(observation)}, batch_size=[1])
        with self._mode:
            return self._nets.policy(td).get("action")[0].double().numpy()


@dataclass(frozen=True)
class ExpertSetup:
    """What trains a task's expert and keys it: its environment as the state sees it, PPO settings, seed."""

    env: SuiteConfig
    ppo: PPOConfig
    seed: int

    @classmethod
    def of_task(cls, env: SuiteConfig, ppo: PPOConfig, seed: int) -> ExpertSetup:
        """The expert of a task whose policy acts in `env`. The expert sees the state alone: how the task's
        policy reads the embedding (its difference) is not the expert's, so a variant that changes only that
        (cheetah-difference) shares the expert, its data and the fits."""
        return cls(replace(env, embedding_difference=False), ppo, seed)

    def identity(self) -> str:
        """What a data set recorded from this expert names (`expert_identity`)."""
        return expert_identity(self.env, self.ppo, self.seed)

    def ensure(self, experts_dir: Path, show_progress: bool = True) -> Path:
        """The expert's weights: the pinned file, or trained in `experts_dir` first (with a progress bar)."""
        with progress_bar(f"expert {self.env.domain}-{self.env.task}", "batch", show_progress) as progress:
            return ensure_expert(experts_dir, self.env, self.ppo, self.seed, progress)

    def policy(self, path: Path) -> ExpertPolicy:
        """The expert stored at `path` as a policy of single states."""
        return ExpertPolicy(path, self.env, self.ppo)
