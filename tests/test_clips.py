import numpy as np

from mftcn_bench.data.clips import clip_indices, clip_offsets


def test_clip_is_current_and_previous_frames_at_stride():
    assert clip_offsets(3, 3).tolist() == [-6, -3, 0]
    assert clip_indices(np.array([10]), 3, 3).tolist() == [[4, 7, 10]]
    assert clip_indices(np.array([0]), 1, 1).tolist() == [[0]]


def test_clip_near_episode_start_repeats_first_frame():
    assert clip_indices(np.array([0, 1, 4]), 3, 2).tolist() == [[0, 0, 0], [0, 0, 1], [0, 2, 4]]
