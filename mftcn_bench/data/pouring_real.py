"""Reader of the real Multiview Pouring dataset (TCN, Sermanet et al.) into the harness's dataset format,
without TensorFlow: TFRecord framing by the `tfrecord` package, messages by its Example protos.

Layout under `real_path` (the TCN release; `labels/` is its `monolithic-labeled/`):
    videos/{train,val,test}/<name>_real_view{0,1}.mov   not read (the TFRecords hold the same frames)
    tfrecords/{train,val,test}/*    unlabelled: one SequenceExample per sequence; context `task` (bytes,
                                    the sequence name) and `len` (int64); feature lists `view0`, `view1`
                                    of per-frame JPEG bytes
    labels/{val,test}/*             labelled: one Example per frame, `image/view0`, `image/view1` (JPEG),
                                    `task` (bytes) and int64 `contact`, `distance`, `liquid_flowing`,
                                    `has_liquid`, `container_angle`
Required: tfrecords/train (the encoders' training sequences) and labels/test; labels/val is read when
present. The train split holds the unlabelled train sequences (labels all -1); val and test hold the
labelled frames grouped into sequences by `task`, in file order. Motion attributes are not in the real
labels: they are stored as -1 (unknown) and get no error. `container_angle` values are mapped to the tilt
classes 90/45/0/-45 by the spec's `real.container_angle_classes` (its coding is not documented).
Frames are decoded with OpenCV and resized to the spec's height x width (area interpolation).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mftcn_bench.core.errors import DataError
from mftcn_bench.data.pouring_labels import LABELS, UNKNOWN

VIEWS = ("view0", "view1")
REAL_LABELS = {"contact": "contact", "within_distance": "distance", "liquid_flowing": "liquid_flowing",
               "has_liquid": "has_liquid", "tilt_angle": "container_angle"}


class RealLayoutError(DataError):
    """A folder that is not in the Multiview Pouring layout."""


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and not p.name.startswith("."))


def check_layout(root: Path) -> dict[str, list[Path]]:
    """The record files of each part, or a one-line error naming the first missing piece."""
    root = Path(root).expanduser()
    if not root.is_dir():
        raise RealLayoutError(f"real pouring data: {root} is not a folder (set task.dataset.real_path)")
    parts: dict[str, list[Path]] = {}
    for part, required in (("tfrecords/train", True), ("labels/test", True), ("labels/val", False)):
        folder = root / part
        files = _files(folder) if folder.is_dir() else []
        if required and not files:
            what = "has no files" if folder.is_dir() else "is missing"
            raise RealLayoutError(f"real pouring data in {root}: {part}/ {what}; expected the Multiview Pouring "
                                  f"layout tfrecords/{{train,val,test}}/ and labels/{{val,test}}/")
        parts[part] = files
    return parts


def _records(path: Path) -> Iterator[bytes]:
    from tfrecord.reader import tfrecord_iterator

    try:
        for record in tfrecord_iterator(str(path)):
            yield bytes(record)
    except RuntimeError as exc:
        raise DataError(f"{path} is not a complete TFRecord file ({exc})") from None


def _parse(message, record: bytes, path: Path):
    from google.protobuf.message import DecodeError

    try:
        message.ParseFromString(record)
    except DecodeError as exc:
        raise DataError(f"{path}: a record is not a {type(message).__name__} ({exc})") from None
    return message


def _bytes(feature_map, key: str, path: Path) -> bytes:
    if key not in feature_map or not feature_map[key].bytes_list.value:
        raise DataError(f"{path}: a record has no bytes feature {key!r}")
    return feature_map[key].bytes_list.value[0]


def _int(feature_map, key: str, path: Path) -> int:
    if key not in feature_map or not feature_map[key].int64_list.value:
        raise DataError(f"{path}: a labelled record has no int64 feature {key!r}")
    return int(feature_map[key].int64_list.value[0])


def decode_jpeg(data: bytes, height: int, width: int) -> np.ndarray:
    """uint8 RGB [height, width, 3] of a JPEG (or PNG) image."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise DataError("a frame's image bytes cannot be decoded as JPEG/PNG")
    image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def scan(root: Path) -> list[list[Any]]:
    """The sequences of each split, in order: [split, file (relative to root), key, frames]; key is the
    record number of an unlabelled sequence, the `task` name of a labelled one."""
    from tfrecord import example_pb2

    root = Path(root).expanduser()
    parts = check_layout(root)
    out: list[list[Any]] = []
    for path in parts["tfrecords/train"]:
        for number, record in enumerate(_records(path)):
            sequence = _parse(example_pb2.SequenceExample(), record, path)
            frames = len(sequence.feature_lists.feature_list[VIEWS[0]].feature)
            out.append(["train", str(path.relative_to(root)), number, frames])
    for split in ("val", "test"):
        counts: dict[tuple[str, str], int] = {}
        for path in parts[f"labels/{split}"]:
            for record in _records(path):
                example = _parse(example_pb2.Example(), record, path)
                key = (str(path.relative_to(root)), _bytes(example.features.feature, "task", path).decode())
                counts[key] = counts.get(key, 0) + 1
        out += [[split, file, task, n] for (file, task), n in counts.items()]
    return out


def angle_class(value: int, coding: list[int]) -> int:
    """Tilt class index (0 = 90 deg ... 3 = -45 deg) of a stored container_angle value."""
    if value not in coding:
        raise DataError(f"container_angle value {value} is not in real.container_angle_classes {coding}; set it "
                        f"to the stored values of the classes 90, 45, 0, -45 degrees")
    return coding.index(value)


def collect_real_episode(config: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
    """Episode `index` (the index-th entry of config["sequences"]) decoded from the TFRecords."""
    from tfrecord import example_pb2

    root = Path(config["real_path"]).expanduser()
    split, file, key, _ = config["sequences"][index]
    path = root / file
    height, width = int(config["height"]), int(config["width"])
    if split == "train":
        for number, record in enumerate(_records(path)):
            if number == key:
                lists = _parse(example_pb2.SequenceExample(), record, path).feature_lists.feature_list
                views = [[decode_jpeg(f.bytes_list.value[0], height, width) for f in lists[v].feature]
                         for v in VIEWS]
                if len(views[0]) != len(views[1]):
                    raise DataError(f"{path}: sequence {key} has {len(views[0])} frames in view0 but "
                                    f"{len(views[1])} in view1")
                frames = np.stack([np.stack(v) for v in views])
                labels = np.full((frames.shape[1], len(LABELS)), UNKNOWN, dtype=np.int8)
                break
        else:
            raise DataError(f"{path} has no sequence number {key}; the data changed since it was scanned")
    else:
        coding = list(config["real"]["container_angle_classes"])
        images, rows = [], []
        for record in _records(path):
            features = _parse(example_pb2.Example(), record, path).features.feature
            if _bytes(features, "task", path).decode() != key:
                continue
            images.append([decode_jpeg(_bytes(features, f"image/{v}", path), height, width) for v in VIEWS])
            row = [UNKNOWN] * len(LABELS)
            for name, stored in REAL_LABELS.items():
                value = _int(features, stored, path)
                row[LABELS.index(name)] = angle_class(value, coding) if name == "tilt_angle" else value
            rows.append(row)
        if not images:
            raise DataError(f"{path} has no labelled frames of sequence {key!r}; the data changed since it was "
                            f"scanned")
        frames = np.stack([np.stack([views[v] for views in images]) for v in range(len(VIEWS))])
        labels = np.array(rows, dtype=np.int8)
    length = frames.shape[1]
    return {"frames": frames, "state": np.zeros((length, 0)), "action": np.zeros((length, 0), np.float32),
            "labels": labels}


def real_dataset_config(dataset: Mapping[str, Any]) -> dict[str, Any]:
    """The dataset config of real data: the spec's image size and coding, plus the scanned sequences (and
    the files' sizes, so changed data is a different dataset)."""
    root = Path(dataset["real_path"]).expanduser()
    shortest = int(dataset["real"]["min_train_frames"])
    sequences = [s for s in scan(root) if s[0] != "train" or s[3] >= shortest]
    if not any(s[0] == "train" for s in sequences):
        raise DataError(f"real pouring data in {root}: no train sequence has real.min_train_frames = {shortest} "
                        f"frames or more")
    counts = {split: sum(1 for s in sequences if s[0] == split) for split in ("train", "val", "test")}
    files = sorted({s[1] for s in sequences})
    return {"name": "pouring-real", "source": "real", "real_path": str(root.resolve()),
            "cameras": list(VIEWS), "height": dataset["height"], "width": dataset["width"],
            "train_episodes": counts["train"], "val_episodes": counts["val"], "test_episodes": counts["test"],
            "episode_length": max(s[3] for s in sequences), "seed": dataset["seed"],
            "real": dict(dataset["real"]), "sequences": sequences,
            "file_sizes": {f: (root / f).stat().st_size for f in files}}
