import json

import numpy as np
import pytest

from mftcn_bench.core.errors import DataError
from mftcn_bench.data.chunks import read_chunk, write_chunk
from mftcn_bench.data.dataset import MultiViewDataset, ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config


def test_chunks_are_byte_deterministic_and_checked(tmp_path):
    arrays = {"frames": np.arange(600, dtype=np.uint8).reshape(2, 3, 10, 10), "state": np.ones((3, 4))}
    sha1 = write_chunk(tmp_path / "a.npz", arrays)
    sha2 = write_chunk(tmp_path / "b.npz", arrays)
    assert sha1 == sha2 and (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    back = read_chunk(tmp_path / "a.npz", sha1)
    assert np.array_equal(back["frames"], arrays["frames"])
    with pytest.raises(DataError, match="does not match its checksum"):
        read_chunk(tmp_path / "a.npz", "0" * 64)


def test_dataset_is_reused_for_the_same_config(tmp_path):
    calls = []

    def counting(config, index):
        calls.append(index)
        return synthetic_collector(config, index)

    a = ensure_dataset(tmp_path, synthetic_config(), counting, show_progress=False)
    b = ensure_dataset(tmp_path, synthetic_config(), counting, show_progress=False)
    assert calls == [0, 1, 2, 3] and a.root == b.root and a.fingerprint == b.fingerprint
    assert a.episodes("train") == [0, 1, 2] and a.episodes("test") == [3]
    c = ensure_dataset(tmp_path, synthetic_config(seed=1), counting, show_progress=False)
    assert c.root != a.root and c.fingerprint != a.fingerprint
    manifest = json.loads((a.root / "manifest.json").read_text())
    assert manifest["versions"]["mftcn-bench"] and len(manifest["chunks"]) == 4


def test_interrupted_collection_resumes_without_redoing_chunks(tmp_path):
    calls = []

    def dies_at_2(config, index):
        calls.append(index)
        if index == 2 and calls.count(2) == 1:
            raise KeyboardInterrupt
        return synthetic_collector(config, index)

    with pytest.raises(KeyboardInterrupt):
        ensure_dataset(tmp_path, synthetic_config(), dies_at_2, show_progress=False)
    dataset = ensure_dataset(tmp_path, synthetic_config(), dies_at_2, show_progress=False)
    assert calls == [0, 1, 2, 2, 3]
    # The same collector (its code is part of the id) collecting from scratch gives the same data.
    fresh = ensure_dataset(tmp_path / "other", synthetic_config(), dies_at_2, show_progress=False)
    assert dataset.fingerprint == fresh.fingerprint


def test_episode_contents_and_errors(tmp_path):
    dataset = ensure_dataset(tmp_path, synthetic_config(), synthetic_collector, show_progress=False)
    episode = dataset.load(1)
    assert episode.frames.shape == (2, 40, 8, 12, 3) and episode.length == 40
    assert episode.frames[1, 5, 0, 0, 0] == 100 + 7 + 5
    with pytest.raises(DataError, match="no episode 9"):
        dataset.load(9)
    with pytest.raises(DataError, match="unknown split"):
        dataset.episodes("validation")
    assert dataset.episodes("val") == [] and episode.labels is None
    (dataset.root / "ep00002.npz").write_bytes(b"garbage")
    with pytest.raises(DataError, match="checksum"):
        MultiViewDataset(dataset.root).load(2)


def test_empty_dataset_is_refused(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"id": "x", "config": {}, "chunks": []}))
    with pytest.raises(DataError, match="empty"):
        MultiViewDataset(tmp_path)
    with pytest.raises(DataError, match="at least 1 train"):
        ensure_dataset(tmp_path, synthetic_config(train_episodes=0), synthetic_collector, show_progress=False)


def test_val_split_and_labels_are_kept(tmp_path):
    def labelled(config, index):
        arrays = synthetic_collector(config, index)
        arrays["labels"] = np.full((len(arrays["state"]), 2), index % 2, dtype=np.int8)
        return arrays

    dataset = ensure_dataset(tmp_path, synthetic_config(val_episodes=2), labelled, show_progress=False)
    assert dataset.episodes("train") == [0, 1, 2] and dataset.episodes("val") == [3, 4]
    assert dataset.episodes("test") == [5]
    labels = dataset.load(4).labels
    assert labels.shape == (40, 2) and labels.dtype == np.int8 and (labels == 0).all()
    with pytest.raises(DataError, match="val_episodes must be >= 0"):
        ensure_dataset(tmp_path, synthetic_config(val_episodes=-1), labelled, show_progress=False)
