"""Pictures of a dataset episode: a contact sheet (PNG) of every view with per-frame labels, and a video.

Both are drawn with OpenCV. The sheet has one row per view and `columns` frames evenly spaced over the
episode, each enlarged by `scale` and captioned with its time index and the labels that are set; the video
shows the views side by side with the same captions (mp4v).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from mftcn_bench.core.errors import DataError

FONT = cv2.FONT_HERSHEY_SIMPLEX


def caption_lines(labels: np.ndarray | None, names: Sequence[str], t: int,
                  formats: dict[str, Sequence[str]] | None = None) -> list[str]:
    """Text for frame t: its index, then each label that is set (multi-class labels by class name)."""
    lines = [f"t={t}"]
    if labels is None:
        return lines
    for name, value in zip(names, labels[t], strict=True):
        if formats and name in formats:
            if 0 <= int(value) < len(formats[name]):
                lines.append(f"{name}={formats[name][int(value)]}")
        elif int(value) == 1:
            lines.append(name)
    return lines


def _captioned(frame: np.ndarray, lines: Sequence[str], scale: int, panel: int) -> np.ndarray:
    """RGB frame enlarged `scale` times above a white text panel `panel` pixels high (BGR out)."""
    big = cv2.resize(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), None, fx=scale, fy=scale,
                     interpolation=cv2.INTER_NEAREST)
    text = np.full((panel, big.shape[1], 3), 255, dtype=np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(text, line, (3, 11 + 11 * i), FONT, 0.32, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([big, text], axis=0)


def contact_sheet(frames: np.ndarray, labels: np.ndarray | None, names: Sequence[str], columns: int = 8,
                  scale: int = 1, formats: dict[str, Sequence[str]] | None = None,
                  view_names: Sequence[str] | None = None) -> np.ndarray:
    """BGR image: one row per view of `columns` evenly spaced frames of frames [V, T, H, W, 3]."""
    if frames.ndim != 5 or frames.shape[1] == 0:
        raise DataError(f"expected frames [views, T, H, W, 3] with T > 0, got shape {frames.shape}")
    times = np.unique(np.linspace(0, frames.shape[1] - 1, columns).round().astype(int))
    panel = 14 + 11 * (len(names) + 1)
    rows = []
    for v in range(frames.shape[0]):
        tiles = []
        for t in times:
            lines = caption_lines(labels, names, int(t), formats)
            if v > 0:
                lines = lines[:1]  # labels are shared by the views: print them once, under the first view
            tiles.append(_captioned(frames[v, t], lines, scale, panel if v == 0 else 16))
            tiles.append(np.full((tiles[-1].shape[0], 2, 3), 255, dtype=np.uint8))
        row = np.concatenate(tiles, axis=1)
        if view_names:
            cv2.putText(row, view_names[v], (4, 14), FONT, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(row)
    return np.concatenate(rows, axis=0)


def write_video(path: Path, frames: np.ndarray, labels: np.ndarray | None, names: Sequence[str], fps: float,
                scale: int = 2, formats: dict[str, Sequence[str]] | None = None) -> Path:
    """An mp4 (mp4v) of all views side by side, captioned with the labels."""
    panel = 14 + 11 * (len(names) + 1)
    first = _video_frame(frames, labels, names, 0, scale, panel, formats)
    height, width = first.shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (width, height))
    if not writer.isOpened():
        raise DataError(f"cannot write video {path} (OpenCV has no mp4v encoder here)")
    try:
        for t in range(frames.shape[1]):
            writer.write(first if t == 0 else _video_frame(frames, labels, names, t, scale, panel, formats))
    finally:
        writer.release()
    return path


def _video_frame(frames, labels, names, t, scale, panel, formats) -> np.ndarray:
    lines = caption_lines(labels, names, t, formats)
    tiles = [_captioned(frames[v, t], lines if v == 0 else lines[:1], scale, panel) for v in range(frames.shape[0])]
    return np.concatenate(tiles, axis=1)


def show_episode(dataset, split: str, position: int, out_dir: Path, columns: int = 8,
                 names: Sequence[str] = (), formats: dict[str, Sequence[str]] | None = None) -> list[Path]:
    """Write `<dataset>-<split><position>.png` (contact sheet) and `.mp4` of one episode into `out_dir`."""
    episodes = dataset.episodes(split)
    if not 0 <= position < len(episodes):
        raise DataError(f"the {split} split has {len(episodes)} episodes; --episode must be in 0..{len(episodes) - 1}")
    episode = dataset.load(episodes[position])
    labels = episode.labels if names and episode.labels is not None else None
    names = names if labels is not None else ()
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = out_dir / f"{dataset.config['name']}-{split}{position}"
    scale = max(1, 160 // max(dataset.image_shape))
    sheet = contact_sheet(episode.frames, labels, names, columns, scale, formats, dataset.cameras)
    png = stem.with_suffix(".png")
    if not cv2.imwrite(str(png), sheet):
        raise DataError(f"cannot write {png}")
    fps = float(dataset.config.get("fps", 30))
    return [png, write_video(stem.with_suffix(".mp4"), episode.frames, labels, names, fps, scale, formats)]
