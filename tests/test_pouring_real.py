"""The real Multiview Pouring reader on a small fixture written here in the dataset's exact format."""

import struct

import crc32c
import cv2
import numpy as np
import pytest
from tfrecord import example_pb2
from tfrecord.writer import TFRecordWriter

from mftcn_bench.cli import main
from mftcn_bench.core.errors import DataError
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.pouring_labels import LABELS
from mftcn_bench.data.pouring_real import RealLayoutError, check_layout
from mftcn_bench.tasks.pouring import PouringTask

H, W = 24, 32  # stored frame size; the dataset resizes to 8 x 12


def masked_crc(data: bytes) -> bytes:
    crc = crc32c.crc32c(data)
    return struct.pack("<I", (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF)


def write_records(path, messages):
    """TFRecord framing: uint64 length, masked crc32c of the length, data, masked crc32c of the data."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        for message in messages:
            data = message.SerializeToString()
            length = struct.pack("<Q", len(data))
            f.write(length + masked_crc(length) + data + masked_crc(data))


def jpeg(value: int) -> bytes:
    image = np.full((H, W, 3), value, dtype=np.uint8)
    image[:, :, 0] = 255 - value  # OpenCV writes BGR: blue differs, so the reader's RGB order is checked
    return cv2.imencode(".jpg", image)[1].tobytes()


def sequence(name: str, length: int, offset: int) -> example_pb2.SequenceExample:
    seq = example_pb2.SequenceExample()
    seq.context.feature["task"].bytes_list.value.append(name.encode())
    seq.context.feature["len"].int64_list.value.append(length)
    for view in (0, 1):
        for t in range(length):
            seq.feature_lists.feature_list[f"view{view}"].feature.add().bytes_list.value.append(
                jpeg(offset + 2 * t + 40 * view))
    return seq


def labelled(name: str, t: int, angle: int) -> example_pb2.Example:
    ex = example_pb2.Example()
    f = ex.features.feature
    f["image/view0"].bytes_list.value.append(jpeg(10 + 20 * t))
    f["image/view1"].bytes_list.value.append(jpeg(200 - 20 * t))
    f["task"].bytes_list.value.append(name.encode())
    for key, value in (("contact", t % 2), ("distance", int(t > 2)), ("liquid_flowing", 0), ("has_liquid", 1),
                       ("container_angle", angle)):
        f[key].int64_list.value.append(value)
    return ex


@pytest.fixture
def real_root(tmp_path):
    root = tmp_path / "multiview-pouring"
    write_records(root / "tfrecords" / "train" / "a.tfrecord", [sequence("s0", 35, 0), sequence("s1", 12, 3)])
    write_records(root / "tfrecords" / "train" / "b.tfrecord", [sequence("s2", 31, 5)])
    write_records(root / "labels" / "test" / "test.tfrecord",
                  [labelled("t0", t, t % 4) for t in range(6)] + [labelled("t1", t, 3) for t in range(5)])
    write_records(root / "labels" / "val" / "val.tfrecord", [labelled("v0", t, 0) for t in range(3)])
    (root / "videos" / "train").mkdir(parents=True)
    return root


def real_task(root, coding=(3, 2, 1, 0)):
    dataset = {"source": "real", "real_path": str(root), "cameras": ["fixed", "orbit"], "height": 8, "width": 12,
               "seed": 0, "real": {"container_angle_classes": list(coding), "min_train_frames": 30}}
    return PouringTask({"name": "pouring", "evaluation": {"split": "test"}, "dataset": dataset}, seed=0)


def test_fixture_framing_is_the_tfrecord_format(tmp_path):
    from tfrecord.reader import tfrecord_iterator

    data = labelled("x", 1, 2).SerializeToString()
    assert masked_crc(data) == TFRecordWriter.masked_crc(data)  # the reference implementation's checksum
    write_records(tmp_path / "r", [labelled("x", 1, 2), labelled("y", 2, 0)])
    back = [example_pb2.Example.FromString(bytes(r)) for r in tfrecord_iterator(str(tmp_path / "r"))]
    assert [e.features.feature["task"].bytes_list.value[0] for e in back] == [b"x", b"y"]


def test_reader_builds_train_val_test_episodes_with_labels(real_root, tmp_path):
    task = real_task(real_root)
    config = task.dataset_config
    assert (config["train_episodes"], config["val_episodes"], config["test_episodes"]) == (2, 1, 2)
    dataset = ensure_dataset(tmp_path / "datasets", config, task.collector, show_progress=False)
    assert dataset.cameras == ["view0", "view1"] and dataset.image_shape == (8, 12)
    train = [dataset.load(i) for i in dataset.episodes("train")]
    assert [e.length for e in train] == [35, 31], "the 12-frame sequence is below min_train_frames"
    first = train[0]
    assert first.frames.shape == (2, 35, 8, 12, 3) and (first.labels == -1).all()
    assert abs(int(first.frames[0, 10, 4, 6, 0]) - 20) <= 3 and abs(int(first.frames[1, 10, 4, 6, 0]) - 60) <= 3
    assert abs(int(first.frames[0, 10, 4, 6, 2]) - 235) <= 3, "frames are RGB"
    t0, t1 = (dataset.load(i) for i in dataset.episodes("test"))
    assert t0.length == 6 and t1.length == 5
    col = {name: t0.labels[:, i] for i, name in enumerate(LABELS)}
    assert col["contact"].tolist() == [0, 1, 0, 1, 0, 1] and col["within_distance"].tolist() == [0, 0, 0, 1, 1, 1]
    assert col["tilt_angle"].tolist() == [3, 2, 1, 0, 3, 2], "stored 0..3 mapped through the coding (3, 2, 1, 0)"
    assert (col["has_liquid"] == 1).all() and (col["reaching"] == -1).all() and (col["coming_down"] == -1).all()
    assert abs(int(t0.frames[1, 2, 0, 0, 0]) - 160) <= 3


def test_task_scores_real_data_without_motion_labels(real_root, tmp_path):
    task = real_task(real_root)
    dataset = ensure_dataset(tmp_path / "datasets", task.dataset_config, task.collector, show_progress=False)

    class Pixels:
        from mftcn_bench.encoders.base import EncoderInfo

        info = EncoderInfo("pixels", 1, 1, (8, 12), 3, 0)
        needs_fit = False

        def embed(self, clips):
            return clips.frames[:, -1].mean(axis=(1, 2)).astype(np.float32)

    metrics = task.evaluate(Pixels(), dataset).metrics
    assert metrics["motion_error"] is None and metrics["error_reaching"] is None
    assert 0 <= metrics["static_error"] <= 100 and metrics["alignment_error"] is not None


def test_wrong_layout_is_one_line_naming_what_is_missing(real_root, tmp_path, capsys, monkeypatch):
    for path in (real_root / "labels" / "test").iterdir():
        path.unlink()
    with pytest.raises(RealLayoutError, match=r"labels/test/ has no files"):
        real_task(real_root)
    (real_root / "labels" / "test").rmdir()
    with pytest.raises(RealLayoutError, match=r"labels/test/ is missing; expected the Multiview Pouring layout"):
        check_layout(real_root)
    with pytest.raises(RealLayoutError, match=r"tfrecords/train/ is missing"):
        check_layout(real_root / "labels")
    monkeypatch.setenv("MFTCN_BENCH_HOME", str(tmp_path / "home"))
    code = main(["data", "collect", "pouring", "--preset", "smoke", "--no-progress", "--set",
                 "task.dataset.source=real", "--set", f"task.dataset.real_path={tmp_path / 'nowhere'}"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "is not a folder" in err


def test_corrupt_records_and_unknown_angle_codes_are_data_errors(real_root, tmp_path):
    with pytest.raises(DataError, match="container_angle value 2 is not in real.container_angle_classes"):
        task = real_task(real_root, coding=(0, 1, 5, 3))
        ensure_dataset(tmp_path / "d1", task.dataset_config, task.collector, show_progress=False)
    path = real_root / "tfrecords" / "train" / "b.tfrecord"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(DataError, match="not a complete TFRecord file"):
        real_task(real_root)
