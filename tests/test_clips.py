import numpy as np
import pytest

from mftcn_bench.data.clips import clip_indices, clip_offsets


def test_clip_is_current_and_previous_frames_at_stride():
    assert clip_offsets(3, 3).tolist() == [-6, -3, 0]
    assert clip_indices(np.array([10]), 3, 3).tolist() == [[4, 7, 10]]
    assert clip_indices(np.array([0]), 1, 1).tolist() == [[0]]


def test_clip_near_episode_start_repeats_first_frame():
    assert clip_indices(np.array([0, 1, 4]), 3, 2).tolist() == [[0, 0, 0], [0, 0, 1], [0, 2, 4]]


@pytest.mark.parametrize("as_torch", [False, True])
def test_clip_ring_gives_the_clips_clip_indices_builds(as_torch):
    """Two environments, the second restarting mid-way: every clip equals the recorded episode's clip."""
    import torch

    from mftcn_bench.data.clips import ClipRing

    frames, stride, length, restart = 3, 2, 12, 5
    episodes = [np.arange(length) * 10.0, np.arange(restart) + 100.0, np.arange(length - restart) + 200.0]
    ring = ClipRing(frames, stride, 2)
    for t in range(length):
        b_episode, b_t = (1, t) if t < restart else (2, t - restart)
        items = np.array([[episodes[0][t]], [episodes[b_episode][b_t]]])
        ring.push(torch.from_numpy(items) if as_torch else items, np.array([t == 0, t in (0, restart)]))
        got = np.asarray(ring.clip())[..., 0]
        want = [episodes[0][clip_indices(np.array([t]), frames, stride)[0]],
                episodes[b_episode][clip_indices(np.array([b_t]), frames, stride)[0]]]
        assert np.array_equal(got, np.stack(want)), t
    with pytest.raises(ValueError, match="have not started"):
        ClipRing(1, 1, 2).push(np.zeros((2, 1)), np.array([True, False]))
