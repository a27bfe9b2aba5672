"""Contact sheets and videos of an episode."""

import cv2
import numpy as np
import pytest

from mftcn_bench.core.errors import DataError
from mftcn_bench.data.show import caption_lines, contact_sheet, write_video


def episode(views=2, length=20):
    frames = np.zeros((views, length, 16, 16, 3), dtype=np.uint8)
    frames[:, :, :, :, 0] = np.arange(length)[None, :, None, None] * 10
    labels = np.stack([np.arange(length) % 2, np.arange(length) % 3], axis=1).astype(np.int8)
    return frames, labels


def test_sheet_has_a_row_per_view_and_captions_the_labels():
    frames, labels = episode()
    sheet = contact_sheet(frames, labels, ["contact", "tilt"], columns=5, scale=2,
                          formats={"tilt": ["90deg", "45deg", "0deg"]}, view_names=["a", "b"])
    assert sheet.ndim == 3 and sheet.shape[1] == 5 * (32 + 2)
    assert caption_lines(labels, ["contact", "tilt"], 1, {"tilt": ["90deg", "45deg", "0deg"]}) == [
        "t=1", "contact", "tilt=45deg"]
    assert caption_lines(None, [], 3) == ["t=3"]
    with pytest.raises(DataError, match="expected frames"):
        contact_sheet(frames[0], labels, ["contact", "tilt"])


def test_video_has_every_frame(tmp_path):
    frames, labels = episode()
    path = write_video(tmp_path / "v.mp4", frames, labels, ["contact", "tilt"], fps=10, scale=2)
    video = cv2.VideoCapture(str(path))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 20
    ok, first = video.read()
    assert ok and first.shape[1] == 2 * 32
