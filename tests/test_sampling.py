import itertools

import numpy as np
import pytest

from mftcn_bench.core.errors import DataError
from mftcn_bench.data.clips import clip_indices
from mftcn_bench.encoders.sampling import plan_batch, sample_timesteps


@pytest.mark.parametrize("length,count,gap", [(100, 8, 10), (50, 5, 12), (30, 1, 5), (29, 4, 9)])
def test_timesteps_are_in_range_sorted_and_gapped(length, count, gap):
    rng = np.random.default_rng(0)
    for _ in range(200):
        t = sample_timesteps(rng, length, count, gap)
        assert len(t) == count and t.min() >= 0 and t.max() < length
        assert (np.diff(t) >= gap).all()


def test_timesteps_cover_every_valid_configuration_uniformly():
    rng = np.random.default_rng(0)
    length, count, gap = 7, 2, 3
    valid = {c for c in itertools.combinations(range(length), count) if c[1] - c[0] >= gap}
    seen = [tuple(sample_timesteps(rng, length, count, gap)) for _ in range(4000)]
    assert set(seen) == valid
    freq = np.array([seen.count(c) for c in valid]) / len(seen)
    assert np.abs(freq - 1 / len(valid)).max() < 0.03


def test_impossible_request_is_a_clear_error():
    with pytest.raises(DataError, match="cannot sample 5 time steps"):
        sample_timesteps(np.random.default_rng(0), 20, 5, 10)


def test_batch_plan_positive_negative_structure():
    """Row k of every view is one (episode, time); rows never share a frame; gaps >= max(alpha, lookback)."""
    rng = np.random.default_rng(3)
    lengths = {0: 120, 1: 120, 2: 90, 3: 200}
    frames, stride, alpha = 4, 3, 5
    lookback = (frames - 1) * stride + 1
    for _ in range(50):
        plan = plan_batch(rng, [0, 1, 2, 3], lengths, timesteps=12, episodes_per_batch=3,
                          min_gap=max(alpha, lookback))
        assert len(plan.times) == 12 and len(set(plan.episodes.tolist())) == 3
        keys = list(zip(plan.episodes.tolist(), plan.times.tolist(), strict=True))
        assert len(set(keys)) == 12  # every row is a distinct time step: all other rows are negatives
        clips = clip_indices(plan.times, frames, stride)
        for episode in set(plan.episodes.tolist()):
            rows = np.flatnonzero(plan.episodes == episode)
            times = np.sort(plan.times[rows])
            assert (np.diff(times) >= max(alpha, lookback)).all()
            used = [f for r in rows for f in set(clips[r].tolist())]
            assert len(used) == len(set(used)), "clips of different time steps overlap"
