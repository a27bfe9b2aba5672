"""Pouring metrics against brute-force numpy and scikit-learn, and the pouring task on a synthetic labelled
dataset."""

import warnings

import numpy as np
import pytest
from sklearn.metrics import balanced_accuracy_score, pairwise_distances

from mftcn_bench.core.errors import SpecError
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.pouring_labels import (
    LABELS,
    MOTION,
    STATIC,
    TILT_CLASSES,
    class_balance,
    labels_from_state,
    tilt_class,
)
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config
from mftcn_bench.encoders.base import EncoderInfo, embed_episode
from mftcn_bench.tasks.pouring import PouringTask, summarize
from mftcn_bench.tasks.pouring_metrics import (
    alignment_error,
    attribute_errors,
    class_recall_error,
    nearest_other_sequence,
)


def brute_nearest(x, seq):
    d = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    d[seq[:, None] == seq[None, :]] = np.inf
    return d.argmin(axis=1)


def brute_error(truth, retrieved):
    known = truth != -1
    classes = np.unique(truth[known])
    return 1 - np.mean([(retrieved[known][truth[known] == c] == c).mean() for c in classes])


def test_nearest_neighbours_and_errors_match_brute_force():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 5))
    seq = rng.integers(0, 6, size=300)
    labels = np.stack([rng.integers(0, 2, 300), rng.integers(0, 4, 300), rng.integers(-1, 2, 300)], axis=1)
    nearest = nearest_other_sequence(x, seq)
    assert np.array_equal(nearest, brute_nearest(x, seq))
    assert (seq[nearest] != seq).all()
    errors = attribute_errors(x, labels, seq, ["a", "b", "c"])
    for j, name in enumerate("abc"):
        assert errors[name] == pytest.approx(brute_error(labels[:, j], labels[nearest, j]))


def test_class_recall_error_is_one_minus_sklearns_balanced_accuracy():
    """Mean recall over the classes among the (known) queries is sklearn's balanced accuracy, which also
    keeps a class none of whose frames was matched (recall 0) and ignores classes only retrieved."""
    rng = np.random.default_rng(2)
    truth = rng.integers(-1, 4, size=200)
    retrieved = np.where(truth == 3, 2, rng.integers(0, 5, size=200))  # class 3 never matched; 4 never true
    known = truth != -1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # sklearn's note that class 4 is predicted but never true
        expected = 1 - balanced_accuracy_score(truth[known], retrieved[known])
    assert class_recall_error(truth, retrieved) == pytest.approx(expected)


def test_class_without_a_match_counts_as_zero_recall_and_unknown_is_skipped():
    truth = np.array([0, 0, 0, 1, -1])
    retrieved = np.array([0, 0, 1, 0, 1])
    # class 0: recall 2/3; class 1: recall 0 (kept, not skipped as the TCN code would); -1 not queried
    assert class_recall_error(truth, retrieved) == pytest.approx(1 - (2 / 3 + 0) / 2)
    assert class_recall_error(np.array([-1, -1]), np.array([0, 1])) is None


def test_alignment_matches_brute_force_and_is_zero_for_identical_views():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(40, 3)), rng.normal(size=(40, 3))
    knn = ((a[:, None] - b[None]) ** 2).sum(-1).argmin(1)
    assert alignment_error([a, b]) == pytest.approx(np.mean(np.abs(np.arange(40) - knn) / 40))
    assert alignment_error([a, a.copy()]) == 0.0


def test_labels_from_state_thresholds():
    thresholds = {"contact_distance": 0.01, "pour_distance": 0.12, "tilt_boundaries": [67.5, 22.5, -22.5],
                  "flowing_min_beads": 2, "has_liquid_min_beads": 3, "approach_speed": 0.03,
                  "vertical_speed": 0.02}
    t = np.arange(6)
    state = np.zeros((6, 14))
    state[:, 7] = [0.3, 0.2, 0.1, 0.0, 0.0, 0.0]       # hand distance: reaching, then contact
    state[:, 5] = [0.0, 0.0, 0.0, 0.0, 0.05, 0.10]     # container rising while held
    state[:, 6] = [90, 70, 50, 10, -30, -80]           # elevation
    state[:, 8] = [0.2, 0.2, 0.1, 0.1, 0.1, 0.2]
    state[:, 11] = [0, 0, 2, 3, 5, 5]
    state[:, 12] = [0, 1, 2, 5, 0, 0]
    labels = labels_from_state(state, 1.0, thresholds)
    col = {name: labels[:, i] for i, name in enumerate(LABELS)}
    assert labels.dtype == np.int8 and labels.shape == (6, 9)
    assert col["contact"].tolist() == [0, 0, 0, 1, 1, 1]
    assert col["reaching"].tolist() == [1, 1, 1, 0, 0, 0] and not col["receding"].any()
    assert col["going_up"].tolist() == [0, 0, 0, 1, 1, 1] and not col["coming_down"].any()
    assert col["tilt_angle"].tolist() == [0, 0, 1, 2, 3, 3] and TILT_CLASSES[3] == -45
    assert col["within_distance"].tolist() == [0, 0, 1, 1, 1, 0]
    assert col["has_liquid"].tolist() == [0, 0, 0, 1, 1, 1]
    assert col["liquid_flowing"].tolist() == [0, 0, 1, 1, 0, 0]
    assert class_balance(labels)["tilt_angle"] == {0: 2 / 6, 1: 1 / 6, 2: 1 / 6, 3: 2 / 6}
    with pytest.raises(ValueError, match="descending"):
        tilt_class(t, [0, 10, 20])


def labelled_collector(config, index):
    """Synthetic frames; labels are a function of time (so sequences share label patterns). The last three
    attributes are unbalanced (a third of the frames in class 1), where the mean recall over classes and the
    plain accuracy differ."""
    arrays = synthetic_collector(config, index)
    length = len(arrays["state"])
    t = np.arange(length)
    labels = np.stack([(t // (length // 4)) % 2, (t // (length // 4)) % 4] + [t % 2] * 4 + [t % 3 == 0] * 3, axis=1)
    arrays["labels"] = labels.astype(np.int8)
    arrays["state"] = labels.astype(np.float64)  # the "true state" encoder sees the labels
    return arrays


class StateEncoder:
    info = EncoderInfo("state", 1, 1, (8, 12), 9, 0)
    privileged_inputs = ("state",)
    needs_fit = False

    def embed(self, clips):
        return clips.state[:, -1].astype(np.float32)


class NoiseEncoder(StateEncoder):
    def embed(self, clips):
        return np.random.default_rng(int(clips.frames.sum())).normal(size=(len(clips.frames), 9)).astype(np.float32)


def metrics_by_sklearn(encoder, dataset) -> dict[str, float]:
    """The pouring task's metrics recomputed from the encoder's embeddings of the test split with sklearn:
    1-NN among the frames of the other sequences by a full distance matrix, 1 - balanced accuracy per
    attribute, static and motion means, and the cross-view nearest neighbour's time offset; in percent."""
    embeddings, labels, sequences, alignment = [], [], [], []
    for episode in dataset.iter_episodes("test"):
        views = [embed_episode(encoder, episode.frames[v], episode.state) for v in range(len(episode.frames))]
        for view in views:
            embeddings.append(view)
            labels.append(episode.labels)
            sequences.append(np.full(len(view), episode.index))
        offsets = [np.abs(np.arange(len(views[i])) - pairwise_distances(views[i], views[j], metric="sqeuclidean")
                          .argmin(1)) / len(views[i]) for i in range(len(views)) for j in range(i + 1, len(views))]
        alignment.append(np.mean([o.mean() for o in offsets]))
    x, labels, sequences = (np.concatenate(a) for a in (embeddings, labels, sequences))
    distances = pairwise_distances(x.astype(np.float64), metric="sqeuclidean")
    distances[sequences[:, None] == sequences[None, :]] = np.inf
    retrieved = labels[distances.argmin(1)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # classes retrieved that no query has
        errors = {name: 100 * (1 - balanced_accuracy_score(labels[:, j], retrieved[:, j]))
                  for j, name in enumerate(LABELS)}
    return {**{f"error_{k}": v for k, v in errors.items()},
            "static_error": float(np.mean([errors[k] for k in STATIC])),
            "motion_error": float(np.mean([errors[k] for k in MOTION])),
            "alignment_error": 100 * float(np.mean(alignment))}


def task_config(**dataset):
    config = {"name": "pouring", "evaluation": {"split": "test"},
              "dataset": {"source": "sim", "real_path": "", "cameras": ["fixed", "orbit"], "real": {}}}
    config["dataset"].update(dataset)
    return config


def test_pouring_task_scores_a_perfect_encoder_zero_and_noise_high(tmp_path):
    dataset_config = synthetic_config(cameras=["fixed", "orbit"], test_episodes=3, episode_length=40)
    dataset = ensure_dataset(tmp_path, dataset_config, labelled_collector, show_progress=False)
    task = PouringTask(task_config(**dataset_config), seed=0)
    good = task.evaluate(StateEncoder(), dataset).metrics
    bad = task.evaluate(NoiseEncoder(), dataset).metrics
    assert good["static_error"] == 0.0 and good["motion_error"] == 0.0
    expected = metrics_by_sklearn(NoiseEncoder(), dataset)
    assert {k: bad[k] for k in expected} == pytest.approx(expected)
    assert bad["static_error"] > 0 and bad["alignment_error"] > 0  # noise is not a perfect encoder
    assert good["eval_sequences"] == 3 and good["eval_frames"] == 3 * 2 * 40
    assert set(summarize(dict.fromkeys(LABELS, 0.5), 0.1)) == {f"error_{k}" for k in LABELS} | {
        "static_error", "motion_error", "alignment_error"}
    rows = task.table(good)
    assert [r["attribute"] for r in rows][-3:] == ["Static (mean)", "Motion (mean)", "Alignment"]


def test_pouring_task_refuses_bad_settings():
    with pytest.raises(SpecError, match="dataset.source must be one of sim, real"):
        PouringTask(task_config(source="video"), 0)
    with pytest.raises(SpecError, match="needs task.dataset.real_path"):
        PouringTask(task_config(source="real"), 0)
    with pytest.raises(SpecError, match="evaluation.split must be one of val, test"):
        PouringTask({**task_config(), "evaluation": {"split": "train"}}, 0)
    with pytest.raises(SpecError, match="needs two of the cameras"):
        PouringTask(task_config(cameras=["fixed", "top"]), 0)
