"""The pouring metrics (after the TCN evaluation code): cross-sequence 1-NN attribute errors and cross-view
alignment error.

- Attribute error: every frame (of every view) takes the labels of its nearest embedding, by squared
  Euclidean distance, among all frames of all OTHER sequences. Per attribute, recall of a class = the share
  of its frames whose neighbour has the same label; error = 1 - the mean recall over the classes present
  among the queries. Unlike the TCN code, a class none of whose frames found a match counts with recall 0
  instead of being left out of the mean. Frames whose label is unknown (-1) are not queried for that
  attribute; an attribute with no known label has no error (None).
- Alignment error: per sequence and pair of views (i < j), for each frame t of view i the time index of
  its nearest neighbour in view j; mean |t - t_knn| / sequence length over the frames, then over the
  sequences and pairs.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from sklearn.neighbors import NearestNeighbors

UNKNOWN = -1


def nearest_other_sequence(embeddings: np.ndarray, sequences: np.ndarray) -> np.ndarray:
    """For every row, the index of its nearest row (squared Euclidean) with a different sequence id."""
    embeddings = np.asarray(embeddings, dtype=np.float64)
    sequences = np.asarray(sequences)
    out = np.full(len(embeddings), -1, dtype=np.int64)
    for seq in np.unique(sequences):
        query = np.flatnonzero(sequences == seq)
        pool = np.flatnonzero(sequences != seq)
        if len(pool) == 0:
            raise ValueError("nearest-neighbour evaluation needs at least two sequences")
        search = NearestNeighbors(n_neighbors=1, algorithm="brute", metric="sqeuclidean").fit(embeddings[pool])
        _, nearest = search.kneighbors(embeddings[query])
        out[query] = pool[nearest[:, 0]]
    return out


def class_recall_error(truth: np.ndarray, retrieved: np.ndarray) -> float | None:
    """1 - mean over classes (present among known truths) of the recall@1; None if no truth is known."""
    known = truth != UNKNOWN
    if not known.any():
        return None
    truth, retrieved = truth[known], retrieved[known]
    recalls = [float(np.mean(retrieved[truth == c] == c)) for c in np.unique(truth)]
    return 1.0 - float(np.mean(recalls))


def attribute_errors(embeddings: np.ndarray, labels: np.ndarray, sequences: np.ndarray,
                     names: Sequence[str]) -> dict[str, float | None]:
    """Error (0-1) per attribute of the cross-sequence 1-NN labels; labels [N, len(names)]."""
    nearest = nearest_other_sequence(embeddings, sequences)
    retrieved = labels[nearest]
    return {name: class_recall_error(labels[:, j], retrieved[:, j]) for j, name in enumerate(names)}


def alignment_error(views: Sequence[np.ndarray]) -> float:
    """Mean |t - t_knn| / T over the frames of view i matched into view j, over view pairs i < j; views are
    [T, D] embeddings of one sequence."""
    errors = []
    for i in range(len(views)):
        for j in range(i + 1, len(views)):
            a, b = np.asarray(views[i], np.float64), np.asarray(views[j], np.float64)
            search = NearestNeighbors(n_neighbors=1, algorithm="brute", metric="sqeuclidean").fit(b)
            _, nearest = search.kneighbors(a)
            errors.append(float(np.mean(np.abs(np.arange(len(a)) - nearest[:, 0]) / len(a))))
    if not errors:
        raise ValueError("alignment needs at least two views")
    return float(np.mean(errors))


def mean_or_none(values: Sequence[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return float(np.mean(known)) if known else None
