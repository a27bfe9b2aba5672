"""pouring: how well a frozen embedding separates the attributes of a pouring scene, and aligns its views.

Encoders are fitted on the train split (both views). Evaluation embeds every frame of both views of every
sequence of the evaluation split (`[evaluation] split`) and reports, in percent (see `pouring_metrics`):
`error_<attribute>` for the nine attributes (1-NN among the frames of all other sequences, 1 - recall
averaged over classes), `static_error` (mean of contact, within_distance, tilt_angle, liquid_flowing,
has_liquid), `motion_error` (mean of reaching, receding, going_up, coming_down) and `alignment_error`
(cross-view nearest neighbour in time). Data: `source = "sim"`, the seeded simulated scene
(`mftcn_bench.data.pouring_sim`), or `source = "real"`, the Multiview Pouring dataset read from `real_path`
(`mftcn_bench.data.pouring_real`; it has no motion labels, so motion errors are None there).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mftcn_bench.core.errors import DataError, SpecError
from mftcn_bench.core.specs import parse_table
from mftcn_bench.data.dataset import Collector, MultiViewDataset
from mftcn_bench.data.pouring_labels import LABELS, MOTION, STATIC, TILT_CLASSES, class_balance
from mftcn_bench.encoders.base import Encoder, embed_episode
from mftcn_bench.tasks.base import TaskResult
from mftcn_bench.tasks.pouring_metrics import alignment_error, attribute_errors, mean_or_none

SOURCES = ("sim", "real")
SPLITS = ("val", "test")


@dataclass(frozen=True)
class EvaluationConfig:
    """The `[evaluation]` table of the task spec."""

    split: str


@dataclass(frozen=True)
class EmbeddedSplit:
    """Every frame of every view of a split: embeddings [N, D], labels [N, 9], sequence and view of each row,
    and the per-sequence view embeddings for alignment."""

    embeddings: np.ndarray
    labels: np.ndarray
    sequences: np.ndarray
    per_sequence: list[list[np.ndarray]]


def percent(value: float | None) -> float | None:
    return None if value is None else 100.0 * value


def summarize(errors: Mapping[str, float | None], alignment: float | None) -> dict[str, float | None]:
    """Metrics in percent: error per attribute, static and motion means, alignment."""
    out: dict[str, float | None] = {f"error_{k}": percent(errors[k]) for k in LABELS}
    out["static_error"] = percent(mean_or_none([errors[k] for k in STATIC]))
    out["motion_error"] = percent(mean_or_none([errors[k] for k in MOTION]))
    out["alignment_error"] = percent(alignment)
    return out


class PouringTask:
    """1-NN attribute classification and cross-view alignment on (simulated or real) pouring videos."""

    label_names = LABELS  # how `mftcn-bench data show` captions the frames
    label_formats = {"tilt_angle": [f"{deg}deg" for deg in TILT_CLASSES]}

    def __init__(self, config: Mapping[str, Any], seed: int) -> None:
        self.config, self.seed = config, seed
        self.evaluation = parse_table(EvaluationConfig, f"task {config['name']!r}", "evaluation",
                                      config["evaluation"])
        if self.evaluation.split not in SPLITS:
            raise SpecError(f"task {config['name']!r}: evaluation.split must be one of {', '.join(SPLITS)}, "
                            f"got {self.evaluation.split!r}")
        dataset = config["dataset"]
        self.source = dataset["source"]
        if self.source not in SOURCES:
            raise SpecError(f"task {config['name']!r}: dataset.source must be one of {', '.join(SOURCES)}, "
                            f"got {self.source!r}")
        if self.source == "real":
            if not dataset["real_path"]:
                raise SpecError("dataset.source = \"real\" needs task.dataset.real_path, the folder of the "
                                "Multiview Pouring data")
            from mftcn_bench.data.pouring_real import real_dataset_config

            self._dataset_config = real_dataset_config(dataset)
        else:
            from mftcn_bench.data.pouring_scene import CAMERAS

            unknown = [c for c in dataset["cameras"] if c not in CAMERAS]
            if unknown or len(dataset["cameras"]) < 2:
                raise SpecError(f"pouring-sim needs two of the cameras {', '.join(CAMERAS)}; got {dataset['cameras']}")
            # The collector's code is part of the dataset's identity (`identity.dataset_id`).
            self._dataset_config = {k: v for k, v in dataset.items() if k not in ("real", "real_path")}
        if self.evaluation.split == "val" and int(self._dataset_config.get("val_episodes", 0)) < 2:
            raise SpecError("evaluation.split = \"val\" needs at least 2 val episodes (neighbours come from "
                            "other sequences)")

    @property
    def dataset_config(self) -> Mapping[str, Any]:
        return self._dataset_config

    @property
    def collector(self) -> Collector:
        if self.source == "real":
            from mftcn_bench.data.pouring_real import collect_real_episode

            return collect_real_episode
        from mftcn_bench.data.pouring_sim import collect_episode

        return collect_episode

    def embed_split(self, encoder: Encoder, dataset: MultiViewDataset, split: str) -> EmbeddedSplit:
        embeddings, labels, sequences, per_sequence = [], [], [], []
        for episode in dataset.iter_episodes(split):
            if episode.labels is None:
                raise DataError(f"dataset {dataset.root} has no per-frame labels; pouring needs a pouring dataset")
            state = episode.state if episode.state.shape[1] else None
            views = [embed_episode(encoder, episode.frames[v], state) for v in range(episode.frames.shape[0])]
            per_sequence.append(views)
            for view in views:
                embeddings.append(view)
                labels.append(episode.labels)
                sequences.append(np.full(len(view), episode.index))
        if len(per_sequence) < 2:
            raise DataError(f"the {split} split has {len(per_sequence)} sequence(s); the 1-NN evaluation needs 2 "
                            f"or more")
        return EmbeddedSplit(np.concatenate(embeddings), np.concatenate(labels), np.concatenate(sequences),
                             per_sequence)

    def evaluate(self, encoder: Encoder, dataset: MultiViewDataset, workdir: Path | None = None) -> TaskResult:
        split = self.evaluation.split
        data = self.embed_split(encoder, dataset, split)
        errors = attribute_errors(data.embeddings, data.labels, data.sequences, LABELS)
        alignment = float(np.mean([alignment_error(views) for views in data.per_sequence]))
        metrics = summarize(errors, alignment)
        metrics.update({"eval_sequences": float(len(data.per_sequence)), "eval_frames": float(len(data.labels))})
        balance = class_balance(data.labels)
        notes = [f"{split} split: {len(data.per_sequence)} sequences, {len(data.labels)} frames over "
                 f"{len(dataset.cameras)} views; errors in %, 1-NN among the frames of other sequences.",
                 "Class balance (share of frames): " + "; ".join(
                     f"{name} " + "/".join(f"{balance[name].get(c, 0.0):.0%}" for c in sorted(balance[name]))
                     for name in LABELS if balance[name])]
        if self.source == "sim":
            notes.append("Simulated pouring (exact labels); the paper's figures are on the real Multiview "
                         "Pouring data and are not comparable.")
        return TaskResult(metrics, notes)

    def table(self, metrics: Mapping[str, Any]) -> list[dict[str, Any]]:
        rows = [{"attribute": name, "kind": "static" if name in STATIC else "motion",
                 "error %": metrics.get(f"error_{name}")} for name in LABELS]
        rows += [{"attribute": "Static (mean)", "kind": "summary", "error %": metrics.get("static_error")},
                 {"attribute": "Motion (mean)", "kind": "summary", "error %": metrics.get("motion_error")},
                 {"attribute": "Alignment", "kind": "summary", "error %": metrics.get("alignment_error")}]
        return rows
