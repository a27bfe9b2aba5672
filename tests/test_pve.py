import math

import numpy as np
import pytest
import torch

from mftcn_bench.core.errors import SpecError, TrainingError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config
from mftcn_bench.encoders import pve
from mftcn_bench.encoders.base import ClipBatch, FitBudget
from mftcn_bench.encoders.pve import (
    PVEEncoder,
    conservation_loss,
    controllability_loss,
    inertia_loss,
    prior_terms,
    sample_triplets,
    slowness_loss,
    variation_loss,
)
from mftcn_bench.encoders.training import EpisodePool

MODEL = {"channels": [8, 8], "kernels": [3, 3], "strides": [2, 2], "coords": True}
TRAIN = {"steps": 6, "batch_size": 8, "lr": 1e-3, "weight_decay": 0.0, "camera_index": 0, "episode_pool": 2,
         "pool_refresh_steps": 2, "checkpoint_every": 2, "max_seconds": 0.0, "variation_weight": 1.0,
         "slowness_weight": 1.0, "inertia_weight": 1.0, "conservation_weight": 1.0,
         "controllability_weight": 0.5}


def t(rows):
    return torch.tensor(rows, dtype=torch.float64)


def make(seed=0, frames=2, dim=4, **train):
    spec = EncoderSpec("pve", "pve", "test", frames, 1, dim, MODEL, {**TRAIN, **train})
    return PVEEncoder(spec, image_shape=(8, 12), seed=seed)


def test_variation_by_hand():
    value = variation_loss(t([[0, 0], [1, 1]]), t([[3, 4], [1, 1]]))
    assert value.item() == pytest.approx((math.exp(-5) + 1) / 2)


def test_slowness_by_hand():
    assert slowness_loss(t([[1, 2], [0, 3]])).item() == pytest.approx((5 + 9) / 2)


def test_inertia_by_hand():
    assert inertia_loss(t([[1, 0], [0, 0]]), t([[1, 1], [2, 0]])).item() == pytest.approx((1 + 4) / 2)


def test_conservation_by_hand():
    value = conservation_loss(t([[3, 4], [0, 0]]), t([[0, 0], [1, 0]]))
    assert value.item() == pytest.approx(((0 - 5) ** 2 + (1 - 0) ** 2) / 2)


def test_controllability_one_action_dimension_pairs_with_every_position_dimension():
    action = t([[1], [-1], [1], [-1]])
    acc = t([[2, 0], [0, 0], [2, 1], [0, 1]])
    # dim 0: centred acc [1, -1, 1, -1] -> cov 1; dim 1: centred [-.5, -.5, .5, .5] -> cov 0
    assert controllability_loss(action, acc).item() == pytest.approx(math.exp(-1) + 1)


def test_controllability_pairs_dimension_i_with_action_i():
    action = t([[1, 1], [-1, 1], [1, -1], [-1, -1]])
    acc = t([[2, 1], [-2, -1], [2, 1], [-2, -1]])  # both dims follow action 0, none follows action 1
    assert controllability_loss(action, acc).item() == pytest.approx(math.exp(-2) + 1)


def test_controllability_matches_numpy_covariance():
    rng = np.random.default_rng(0)
    action, acc = rng.normal(size=(50, 1)), rng.normal(size=(50, 3)) + rng.normal(size=(50, 1)) * 0.5
    acc[:, 1] += action[:, 0]
    expected = sum(math.exp(-abs(np.cov(action[:, 0], acc[:, i], bias=True)[0, 1])) for i in range(3))
    assert controllability_loss(torch.from_numpy(action), torch.from_numpy(acc)).item() == pytest.approx(expected)


def test_prior_terms_use_velocities_and_accelerations_of_the_triplets():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(5, 3, 2))
    action = rng.normal(size=(5, 1))
    terms = prior_terms(torch.from_numpy(p), torch.from_numpy(action))
    v_t, v_next = p[:, 1] - p[:, 0], p[:, 2] - p[:, 1]
    acc = v_next - v_t
    others = np.roll(p, 1, axis=0)
    assert terms["variation"].item() == pytest.approx(np.exp(-np.linalg.norm(p - others, axis=2)).mean())
    assert terms["slowness"].item() == pytest.approx(np.mean(np.r_[(v_t ** 2).sum(1), (v_next ** 2).sum(1)]))
    assert terms["inertia"].item() == pytest.approx(((v_next - v_t) ** 2).sum(1).mean())
    speeds = np.linalg.norm(v_next, axis=1) - np.linalg.norm(v_t, axis=1)
    assert terms["conservation"].item() == pytest.approx((speeds ** 2).mean())
    covs = [np.cov(action[:, 0], acc[:, i], bias=True)[0, 1] for i in range(2)]
    assert terms["controllability"].item() == pytest.approx(sum(math.exp(-abs(c)) for c in covs))


def test_triplets_are_consecutive_frames_of_one_view_with_the_middle_action(tmp_path):
    dataset = ensure_dataset(tmp_path, synthetic_config(episode_length=5), synthetic_collector,
                             show_progress=False)
    pool = EpisodePool(dataset, size=3, refresh_steps=0, rng=np.random.default_rng(0))
    frames, actions = sample_triplets(pool, np.random.default_rng(1), 60, camera=1)
    assert frames.shape == (60, 3, 8, 12, 3) and actions.shape == (60, 1)
    values = frames[:, :, 0, 0, 0].astype(int) - 100  # view 1: 100 + 7 * episode + t
    assert (np.diff(values, axis=1) == 1).all()
    middles = set()
    for row, action in zip(values, actions, strict=True):
        found = [(e, row[1] - 7 * e) for e in pool.episodes if 0 <= row[1] - 7 * e < 5
                 and pool.episodes[e].action[row[1] - 7 * e, 0] == action[0]]
        assert len(found) == 1
        middles.add(int(found[0][1]))
    assert middles == {1, 2, 3}  # never the first or last frame


def test_embedding_is_position_and_its_finite_difference():
    encoder = make()
    frames = np.random.default_rng(0).integers(0, 255, (6, 8, 12, 3), dtype=np.uint8)
    out = encoder.embed_episode(frames)
    with torch.no_grad():
        p = encoder.net(torch.from_numpy(frames).permute(0, 3, 1, 2)).numpy()
    assert out.shape == (6, 4)
    assert np.allclose(out[:, :2], p, atol=1e-5)
    assert np.allclose(out[1:, 2:], p[1:] - p[:-1], atol=1e-5)
    assert np.allclose(out[0, 2:], 0)
    clip = frames[[2, 3]][None]
    assert np.allclose(encoder.embed(ClipBatch(clip))[0], out[3], atol=1e-5)


def test_spec_checks():
    with pytest.raises(SpecError, match="frames = 2"):
        make(frames=3)
    with pytest.raises(SpecError, match="even"):
        make(dim=5)
    with pytest.raises(SpecError, match="unknown key.*'smoothness_weight'"):
        make(smoothness_weight=1.0)


def test_training_resumes_bitwise_and_saves(tmp_path):
    dataset = ensure_dataset(tmp_path / "d", synthetic_config(), synthetic_collector, show_progress=False)
    straight = make()
    stats = []
    straight.fit(dataset, FitBudget(6), lambda s, n, st: stats.append(st), tmp_path / "w1")
    assert set(stats[0]) == {"loss", *pve.PRIORS}

    class Killed(Exception):
        pass

    def die_at_5(step, total, stats):
        if step == 5:
            raise Killed

    with pytest.raises(Killed):
        make().fit(dataset, FitBudget(6), die_at_5, tmp_path / "w2")
    resumed = make()
    resumed.fit(dataset, FitBudget(6), lambda *a: None, tmp_path / "w2")
    for p, q in zip(straight.net.parameters(), resumed.net.parameters(), strict=True):
        assert torch.equal(p, q)
    straight.save(tmp_path / "m.pt")
    fresh = make(seed=3)
    fresh.load(tmp_path / "m.pt")
    clip = ClipBatch(np.random.default_rng(0).integers(0, 255, (2, 2, 8, 12, 3), dtype=np.uint8))
    assert np.array_equal(straight.embed(clip), fresh.embed(clip))


def test_nan_loss_stops_with_the_step(tmp_path, monkeypatch):
    dataset = ensure_dataset(tmp_path, synthetic_config(), synthetic_collector, show_progress=False)
    monkeypatch.setattr(pve, "variation_loss", lambda a, b: a.sum() * float("nan"))
    with pytest.raises(TrainingError, match="at step 0"):
        make().fit(dataset, FitBudget(3), lambda *a: None, tmp_path / "w")
