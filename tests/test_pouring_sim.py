"""Simulated pouring: seeded, byte-identical episodes with labels that follow the script."""

import tomllib
from pathlib import Path

import numpy as np
import pytest

from mftcn_bench.core.errors import DataError
from mftcn_bench.data.pouring_labels import LABELS, STATE_COLUMNS
from mftcn_bench.data.pouring_scene import scene_xml
from mftcn_bench.data.pouring_sim import collect_episode

SPEC = Path(__file__).resolve().parents[1] / "tasks" / "pouring.toml"


def tiny_config(**changes):
    config = tomllib.loads(SPEC.read_text())["dataset"]
    config.update({"height": 16, "width": 16, "fps": 6, "time_scale": 0.4, "settle_seconds": 0.4})
    config["scene"] = {**config["scene"], "beads": 16}
    config["pour"] = {**config["pour"], "max_seconds": 30.0, "fast_rate": 40.0}  # time to empty at this scale
    config.update(changes)
    return config


@pytest.fixture(scope="module")
def episode():
    return collect_episode(tiny_config(), 0)


def test_same_seed_gives_byte_identical_frames_and_other_episodes_differ(episode):
    again = collect_episode(tiny_config(), 0)
    assert episode["frames"].shape[:2] == (2, len(episode["state"])) and episode["frames"].dtype == np.uint8
    assert episode["frames"].shape[2:] == (16, 16, 3)
    for key in ("frames", "state", "labels"):
        assert episode[key].tobytes() == again[key].tobytes(), key
    other = collect_episode(tiny_config(), 1)
    assert not np.array_equal(episode["state"][0], other["state"][0])
    assert not np.array_equal(episode["frames"][0], episode["frames"][1]), "the two views differ"


def test_script_grasps_pours_and_puts_back(episode):
    state, labels = episode["state"], episode["labels"]
    col = {name: state[:, i] for i, name in enumerate(STATE_COLUMNS)}
    lab = {name: labels[:, i] for i, name in enumerate(LABELS)}
    assert state.shape[1] == len(STATE_COLUMNS) and labels.shape[1] == len(LABELS)
    beads = col["beads_in_container"] + col["beads_in_recipient"] + col["beads_in_flight"] + col["beads_elsewhere"]
    assert (beads == 16).all()
    assert col["beads_in_container"][0] >= 15, "the beads settle in the container"
    assert col["beads_in_recipient"][-1] >= 10, "most beads end in the recipient"
    assert col["elevation"].min() < -22.5 and col["elevation"][-1] > 85, "tilted past horizontal, then upright"
    assert lab["contact"][0] == 0 and lab["contact"].any() and lab["contact"][-1] == 0
    for name in ("reaching", "receding", "going_up", "coming_down", "liquid_flowing", "has_liquid",
                 "within_distance"):
        assert lab[name].any(), name
    assert set(np.unique(lab["tilt_angle"])) == {0, 1, 2, 3}
    action = episode["action"]
    assert action.shape == (len(state), 4) and action.dtype == np.float32
    timestep = tiny_config()["scene"]["timestep"]
    frame_seconds = round(1 / (6 * timestep)) * timestep
    hand = state[:, 0:3]
    assert np.allclose(action[:-1, :3] * frame_seconds, np.diff(hand, axis=0), atol=1e-6), "commanded velocity"
    assert (action[:, 3] == col["grasped"]).all(), "grasp flag during the frame's motion"
    first_contact = int(np.argmax(lab["contact"]))
    assert lab["reaching"][:first_contact].any() and not lab["receding"][:first_contact].any()


def test_bad_settings_are_one_line_errors():
    with pytest.raises(DataError, match="camera 'top' does not exist in pouring-sim"):
        collect_episode(tiny_config(cameras=["fixed", "top"]), 0)
    with pytest.raises(DataError, match="do not fit in the fill tube"):
        collect_episode(tiny_config(scene={**tiny_config()["scene"], "beads": 200, "fill_tube_height": 0.001}), 0)


def test_scene_has_no_gaps_in_walls():
    xml = scene_xml(tiny_config()["scene"])
    assert xml.count('<geom name="tube_wall') == tiny_config()["scene"]["wall_segments"]
    assert 'euler="0 0 30.0000"' in xml  # wall angles in degrees (MJCF's unit)
