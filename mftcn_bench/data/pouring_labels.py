"""Per-frame pouring attributes from the recorded simulator state, with the thresholds of `[dataset.labels]`.

The state columns of a simulated pouring episode (`STATE_COLUMNS`, float [T, 14]):
    0-2   hand grip point x, y, z (m)
    3-5   container centre x, y, z (m; the middle of its axis)
    6     container elevation (degrees): angle of its axis above the horizontal, 90 upright, negative past
          horizontal
    7     hand-to-container distance (m): from the hand's grip point to the container's outer surface
    8     horizontal distance from the container centre to the recipient's axis (m)
    9     grasp weld active (0/1)
    10    beads inside the container
    11    beads inside the recipient
    12    beads in flight (outside both, above `flight_min_height`, faster than `flight_speed`)
    13    beads elsewhere (spilled, at rest)

The labels (`LABELS`, int8 [T, 9], in this column order):
    contact          hand-to-container distance < contact_distance
    within_distance  container-to-recipient horizontal distance < pour_distance
    tilt_angle       class index of the elevation: 0 = 90 deg (upright), 1 = 45, 2 = 0 (horizontal), 3 = -45;
                     `tilt_boundaries` (descending) separate the classes
    liquid_flowing   beads in flight >= flowing_min_beads
    has_liquid       beads in the recipient >= has_liquid_min_beads
    reaching         no contact and the hand-to-container distance shrinks faster than approach_speed (m/s)
    receding         no contact and that distance grows faster than approach_speed
    going_up         contact and the container centre rises faster than vertical_speed (m/s)
    coming_down      contact and the container centre sinks faster than vertical_speed
Rates are central differences over the frame interval. Real data that lacks an attribute stores -1 there.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

STATE_COLUMNS = ("hand_x", "hand_y", "hand_z", "container_x", "container_y", "container_z", "elevation",
                 "hand_distance", "recipient_distance", "grasped", "beads_in_container", "beads_in_recipient",
                 "beads_in_flight", "beads_elsewhere")
STATIC = ("contact", "within_distance", "tilt_angle", "liquid_flowing", "has_liquid")
MOTION = ("reaching", "receding", "going_up", "coming_down")
LABELS = STATIC + MOTION
TILT_CLASSES = (90, 45, 0, -45)  # degrees named by tilt_angle class index 0..3
UNKNOWN = -1

_COLUMN = {name: i for i, name in enumerate(STATE_COLUMNS)}


def tilt_class(elevation: np.ndarray, boundaries: list[float]) -> np.ndarray:
    """Class index (0 = 90 deg ... 3 = -45 deg) of each elevation; `boundaries` are descending."""
    edges = np.asarray(boundaries, dtype=np.float64)
    if edges.shape != (len(TILT_CLASSES) - 1,) or np.any(np.diff(edges) >= 0):
        raise ValueError(f"tilt_boundaries must be {len(TILT_CLASSES) - 1} descending angles, got {boundaries}")
    return (np.asarray(elevation)[:, None] < edges[None, :]).sum(axis=1)


def labels_from_state(state: np.ndarray, frame_seconds: float, thresholds: Mapping[str, Any]) -> np.ndarray:
    """int8 [T, 9] labels (LABELS order) of one episode's state [T, 14] (STATE_COLUMNS order)."""
    col = {name: state[:, i] for name, i in _COLUMN.items()}
    contact = col["hand_distance"] < thresholds["contact_distance"]
    approach = _rate(col["hand_distance"], frame_seconds)
    rise = _rate(col["container_z"], frame_seconds)
    out = {
        "contact": contact,
        "within_distance": col["recipient_distance"] < thresholds["pour_distance"],
        "tilt_angle": tilt_class(col["elevation"], thresholds["tilt_boundaries"]),
        "liquid_flowing": col["beads_in_flight"] >= thresholds["flowing_min_beads"],
        "has_liquid": col["beads_in_recipient"] >= thresholds["has_liquid_min_beads"],
        "reaching": ~contact & (approach < -thresholds["approach_speed"]),
        "receding": ~contact & (approach > thresholds["approach_speed"]),
        "going_up": contact & (rise > thresholds["vertical_speed"]),
        "coming_down": contact & (rise < -thresholds["vertical_speed"]),
    }
    return np.stack([np.asarray(out[name]).astype(np.int8) for name in LABELS], axis=1)


def _rate(values: np.ndarray, frame_seconds: float) -> np.ndarray:
    if len(values) < 2:
        return np.zeros_like(values)
    return np.gradient(values, frame_seconds)


def class_balance(labels: np.ndarray) -> dict[str, dict[int, float]]:
    """Fraction of labelled frames in each class, per attribute (unknown frames left out)."""
    out: dict[str, dict[int, float]] = {}
    for j, name in enumerate(LABELS):
        column = labels[:, j]
        known = column[column != UNKNOWN]
        values, counts = np.unique(known, return_counts=True)
        out[name] = {int(v): float(c) / max(len(known), 1) for v, c in zip(values, counts, strict=True)}
    return out
