"""Position-Velocity Encoder (PVE, Jonschkowski et al. 2017), trained with robotic priors.

A position encoder maps ONE frame to p_t (the mfTCN base CNN, spatial average, linear layer to
`position_dim = embedding_dim / 2`); the velocity is the finite difference v_t = p_t - p_{t-1}; the
embedding of a clip (frames t-1, t) is [p_t, v_t]. At an episode's first frame the clip repeats that frame,
so v = 0 there (the harness's clip rule).

Training uses one view (`train.camera_index`) of the train split and no decoder. A batch is B consecutive
triplets (t-1, t, t+1) from a pool of decoded episodes, with the action a_t recorded after frame t (it
acts between frames t and t+1). With v_t = p_t - p_{t-1}, v_{t+1} = p_{t+1} - p_t and
acc_{t+1} = v_{t+1} - v_t, the priors are (all expectations are batch means):

- variation       E[exp(-||p_a - p_b||)] over random pairs (each position with the same slot of the
                  batch's previous triplet): different states are far apart;
- slowness        E[||v||^2] over v_t and v_{t+1}: positions change slowly;
- inertia         E[||v_{t+1} - v_t||^2]: velocities change slowly;
- conservation    E[(||v_{t+1}|| - ||v_t||)^2]: the speed changes slowly;
- controllability sum_i exp(-|Cov(a_{t,j(i)}, acc_{t+1,i})|): every position dimension's acceleration
                  covaries with an action dimension. Position dimension i is paired with action dimension
                  j(i) = i mod A; when the action has as many dimensions as the position that is the
                  paper's pairing, and a 1-D action (cartpole) is paired with every position dimension.
                  Cov is the batch's (biased, 1/B) covariance.

The loss is the weighted sum; the weights are `[train]` keys of the spec.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.base import ClipBatch, FitBudget, ProgressFn
from mftcn_bench.encoders.common import MovableEncoder, check_image_shape, map_batches, parse_table, to_images, to_numpy
from mftcn_bench.encoders.frame_cnn import CNNConfig, FrameNet, SingleViewTrainConfig, train_single_view
from mftcn_bench.encoders.training import EpisodePool

PRIORS = ("variation", "slowness", "inertia", "conservation", "controllability")


@dataclass(frozen=True, kw_only=True)
class PVETrainConfig(SingleViewTrainConfig):
    """The `[train]` table of a PVE spec: the common single-view keys plus one weight per prior."""

    variation_weight: float
    slowness_weight: float
    inertia_weight: float
    conservation_weight: float
    controllability_weight: float

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in PRIORS:
            if getattr(self, f"{name}_weight") < 0:
                raise SpecError(f"PVE [train]: {name}_weight must be >= 0")

    def weights(self) -> dict[str, float]:
        return {name: float(getattr(self, f"{name}_weight")) for name in PRIORS}


def variation_loss(p_a: torch.Tensor, p_b: torch.Tensor) -> torch.Tensor:
    """E[exp(-||p_a - p_b||)] over rows of [N, P] pairs."""
    return torch.exp(-torch.linalg.vector_norm(p_a - p_b, dim=-1)).mean()


def slowness_loss(v: torch.Tensor) -> torch.Tensor:
    """E[||v||^2] over rows of [N, P]."""
    return v.pow(2).sum(dim=-1).mean()


def inertia_loss(v_t: torch.Tensor, v_next: torch.Tensor) -> torch.Tensor:
    """E[||v_{t+1} - v_t||^2]."""
    return (v_next - v_t).pow(2).sum(dim=-1).mean()


def conservation_loss(v_t: torch.Tensor, v_next: torch.Tensor) -> torch.Tensor:
    """E[(||v_{t+1}|| - ||v_t||)^2]."""
    speed_t = torch.linalg.vector_norm(v_t, dim=-1)
    speed_next = torch.linalg.vector_norm(v_next, dim=-1)
    return (speed_next - speed_t).pow(2).mean()


def controllability_loss(action: torch.Tensor, acc: torch.Tensor) -> torch.Tensor:
    """sum_i exp(-|Cov(a_{j(i)}, acc_i)|) for actions [N, A] and accelerations [N, P], j(i) = i mod A;
    the covariance is the biased batch estimate (mean of products of centred values)."""
    action = action.to(acc.dtype)
    pairs = torch.arange(acc.shape[1], device=acc.device) % action.shape[1]
    centred_a = action[:, pairs] - action[:, pairs].mean(dim=0)
    centred_acc = acc - acc.mean(dim=0)
    cov = (centred_a * centred_acc).mean(dim=0)
    return torch.exp(-cov.abs()).sum()


def prior_terms(positions: torch.Tensor, action: torch.Tensor) -> dict[str, torch.Tensor]:
    """The five prior losses for positions [B, 3, P] of triplets (t-1, t, t+1) and actions a_t [B, A]."""
    p_prev, p_t, p_next = positions.unbind(dim=1)
    v_t, v_next = p_t - p_prev, p_next - p_t
    width = positions.shape[-1]
    others = torch.roll(positions, shifts=1, dims=0)  # the previous triplet of the batch: a random pair
    return {
        "variation": variation_loss(positions.reshape(-1, width), others.reshape(-1, width)),
        "slowness": slowness_loss(torch.cat([v_t, v_next])),
        "inertia": inertia_loss(v_t, v_next),
        "conservation": conservation_loss(v_t, v_next),
        "controllability": controllability_loss(action, v_next - v_t),
    }


def sample_triplets(pool: EpisodePool, rng: np.random.Generator, count: int,
                    camera: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` consecutive frame triplets (t-1, t, t+1) of one view, uint8 [count, 3, H, W, 3], and the
    action a_t of each, float32 [count, A]. Episodes are drawn uniformly from the pool, t uniformly."""
    members = sorted(pool.episodes)
    picked = rng.choice(members, size=count)
    frames, actions = [], []
    for episode in picked:
        ep = pool.episodes[int(episode)]
        t = int(rng.integers(1, ep.length - 1))
        frames.append(ep.frames[camera, t - 1:t + 2])
        actions.append(ep.action[t])
    return np.stack(frames), np.stack(actions).astype(np.float32)


class PVEEncoder(MovableEncoder):
    """Position from one frame, velocity as its finite difference; embedding [p_t, v_t]."""

    needs_fit = True
    privileged_inputs = ("action",)  # the controllability prior reads the recorded actions during fit

    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        if spec.frames != 2 or spec.stride != 1:
            raise SpecError(f"encoder {spec.name!r}: PVE embeds clips of frames t-1, t (frames = 2, stride = 1), "
                            f"got frames = {spec.frames}, stride = {spec.stride}")
        if spec.embedding_dim % 2:
            raise SpecError(f"encoder {spec.name!r}: embedding_dim = 2 * position_dim must be even, "
                            f"got {spec.embedding_dim}")
        super().__init__(spec, image_shape, seed)
        self.model_config = parse_table(CNNConfig, spec.name, "model", spec.model)
        self.train_config = parse_table(PVETrainConfig, spec.name, "train", spec.train)
        self.position_dim = spec.embedding_dim // 2
        torch.manual_seed(seed)
        self.net = FrameNet(self.model_config, self.position_dim).eval()

    def batch_loss(self, pool: EpisodePool, rng: np.random.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        """The weighted prior loss of one sampled batch, and each prior's value."""
        config = self.train_config
        frames, actions = sample_triplets(pool, rng, config.batch_size, config.camera_index)
        images = to_images(frames).to(self.device)
        positions = self.net(images.reshape(-1, *images.shape[2:])).reshape(len(frames), 3, -1)
        terms = prior_terms(positions, torch.from_numpy(actions).to(self.device))
        weights = config.weights()
        loss = sum(weights[name] * value for name, value in terms.items())
        return loss, {name: float(value.detach()) for name, value in terms.items()}

    def fit(self, dataset: MultiViewDataset, budget: FitBudget, progress: ProgressFn,
            workdir: Path) -> dict[str, float]:
        check_image_shape(self.image_shape, dataset)
        return train_single_view(self.net, dataset, self.train_config, budget, progress, workdir,
                                 seed=self.seed, min_length=3, batch_loss=self.batch_loss, device=self.device)

    @torch.no_grad()
    def embed(self, clips: ClipBatch) -> np.ndarray:
        images = to_images(clips.frames).to(self.device)
        positions = self.net(images.reshape(-1, *images.shape[2:])).reshape(len(images), 2, -1)
        return to_numpy(torch.cat([positions[:, 1], positions[:, 1] - positions[:, 0]], dim=1))

    @torch.no_grad()
    def embed_episode(self, frames: np.ndarray, state: np.ndarray | None = None,
                      batch_size: int = 256) -> np.ndarray:
        """[p_t, p_t - p_{t-1}] for every frame of one view [T, H, W, 3]: one CNN pass per frame."""
        positions = map_batches(lambda rows: self.net(rows.to(self.device)), to_images(frames), batch_size)
        previous = torch.from_numpy(clip_indices(np.arange(len(frames)), 2, 1)[:, 0]).to(self.device)
        return to_numpy(torch.cat([positions, positions - positions[previous]], dim=1))
