"""PixelPCAEncoder: the smallest honest encoder: PCA of downsampled grey clips.

It shows the whole contract of mftcn_bench.encoders.base.Encoder: metadata, fit with a budget and
progress, embed a batch of clips, save and load.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from sklearn.decomposition import PCA

from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.encoders.base import ClipBatch, EncoderInfo, FitBudget, ProgressFn


class PixelPCAEncoder:
    def __init__(self, spec: EncoderSpec, image_shape: tuple[int, int], seed: int) -> None:
        self.spec, self.image_shape, self.seed = spec, tuple(image_shape), seed
        self.step = int(spec.model["downsample"])
        self.pca: PCA | None = None

    @property
    def info(self) -> EncoderInfo:
        params = 0 if self.pca is None else int(self.pca.components_.size + self.pca.mean_.size)
        return EncoderInfo(self.spec.name, self.spec.frames, self.spec.stride, self.image_shape,
                           self.spec.embedding_dim, params)

    @property
    def needs_fit(self) -> bool:
        return True

    def _features(self, frames: np.ndarray) -> np.ndarray:
        """uint8 clips [B, n, H, W, 3] -> float [B, n * h * w] grey, downsampled."""
        grey = frames[:, :, :: self.step, :: self.step].mean(axis=-1) / 255.0
        return grey.reshape(len(frames), -1)

    def fit(self, dataset, budget: FitBudget, progress: ProgressFn, workdir: Path) -> dict[str, float]:
        rng = np.random.default_rng(self.seed)
        episodes = dataset.episodes("train")
        per_episode = max(1, budget.steps // len(episodes))
        rows = []
        for done, index in enumerate(episodes, start=1):
            episode = dataset.load(index)
            times = rng.integers(0, episode.length, size=per_episode)
            clips = episode.frames[0][clip_indices(times, self.spec.frames, self.spec.stride)]
            rows.append(self._features(clips))
            progress(done, len(episodes), {})
        data = np.concatenate(rows)
        self.pca = PCA(n_components=self.spec.embedding_dim, random_state=self.seed).fit(data)
        return {"explained_variance": float(self.pca.explained_variance_ratio_.sum())}

    def embed(self, clips: ClipBatch) -> np.ndarray:
        return self.pca.transform(self._features(clips.frames)).astype(np.float32)

    def save(self, path: Path) -> None:
        np.savez(path.with_suffix(".npz"), components=self.pca.components_, mean=self.pca.mean_)
        path.write_text(json.dumps({"file": path.with_suffix(".npz").name}))

    def load(self, path: Path) -> None:
        arrays = np.load(path.with_suffix(".npz"))
        self.pca = PCA(n_components=self.spec.embedding_dim)
        self.pca.components_, self.pca.mean_ = arrays["components"], arrays["mean"]
        self.pca.n_features_in_ = arrays["mean"].size
