import json

import numpy as np
import pytest
import torch

from mftcn_bench.core.errors import TrainingError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config
from mftcn_bench.encoders import training
from mftcn_bench.encoders.base import FIT_CURVE, ClipBatch, FitBudget, embed_episode
from mftcn_bench.encoders.mftcn import MfTCNEncoder
from mftcn_bench.encoders.training import EpisodePool, gather_clips

SMALL_CNN = {"name": "small-cnn", "channels": [8, 8], "kernels": [3, 3], "strides": [2, 2], "coords": True}
MODEL = {"adapter_channels": 8, "temporal_channels": 8, "base": SMALL_CNN}
TRAIN = {"steps": 6, "batch_timesteps": 4, "episodes_per_batch": 2, "alpha": 2, "lr": 1e-3,
         "weight_decay": 1e-6, "reg_lambda": 0.002, "episode_pool": 2, "pool_refresh_steps": 2,
         "checkpoint_every": 2, "max_seconds": 0.0}


def make(frames=1, stride=1, dim=16, shape=(8, 12), seed=0, **train):
    spec = EncoderSpec("t", "mftcn", "test", frames, stride, dim, MODEL, {**TRAIN, **train})
    return MfTCNEncoder(spec, image_shape=shape, seed=seed)


@pytest.mark.parametrize("frames,stride,lookback", [(1, 1, 1), (2, 1, 2), (4, 1, 4), (5, 1, 5), (3, 3, 7),
                                                    (4, 4, 13), (5, 7, 29)])
def test_output_shapes_for_lookbacks(frames, stride, lookback):
    encoder = make(frames, stride, dim=8, shape=(24, 32))
    assert encoder.info.lookback == lookback
    clips = np.random.default_rng(0).integers(0, 255, (3, frames, 24, 32, 3), dtype=np.uint8)
    out = encoder.embed(ClipBatch(clips))
    assert out.shape == (3, 8) and out.dtype == np.float32
    episode = np.random.default_rng(1).integers(0, 255, (40, 24, 32, 3), dtype=np.uint8)
    assert embed_episode(encoder, episode).shape == (40, 8)


def test_episode_embedding_equals_embedding_each_clip():
    encoder = make(frames=3, stride=2)
    frames = np.random.default_rng(0).integers(0, 255, (15, 8, 12, 3), dtype=np.uint8)
    fast = encoder.embed_episode(frames)
    for t in (0, 1, 4, 14):
        clip = frames[[max(t - 4, 0), max(t - 2, 0), t]][None]
        assert np.allclose(fast[t], encoder.embed(ClipBatch(clip))[0], atol=1e-5)


def test_gathered_clip_holds_frames_t_minus_ks_of_one_view(tmp_path):
    dataset = ensure_dataset(tmp_path, synthetic_config(), synthetic_collector, show_progress=False)
    pool = EpisodePool(dataset, size=3, refresh_steps=0, rng=np.random.default_rng(0))
    episode = sorted(pool.episodes)[0]
    clips = gather_clips(pool, np.array([episode, episode]), np.array([9, 2]), frames=3, stride=3)
    assert clips.shape == (2, 2, 3, 8, 12, 3)
    for view in range(2):
        values = clips[view, :, :, 0, 0, 0].astype(int) - view * 100 - episode * 7
        assert values.tolist() == [[3, 6, 9], [0, 0, 2]]


def test_save_load_roundtrip(tmp_path):
    a, b = make(frames=2, seed=0), make(frames=2, seed=1)
    clips = np.random.default_rng(0).integers(0, 255, (2, 2, 8, 12, 3), dtype=np.uint8)
    assert not np.allclose(a.embed(ClipBatch(clips)), b.embed(ClipBatch(clips)))
    a.save(tmp_path / "m.pt")
    b.load(tmp_path / "m.pt")
    assert np.array_equal(a.embed(ClipBatch(clips)), b.embed(ClipBatch(clips)))


def test_training_resumes_bitwise_after_interruption(tmp_path):
    dataset = ensure_dataset(tmp_path / "d", synthetic_config(), synthetic_collector, show_progress=False)
    straight = make(frames=2)
    straight.fit(dataset, FitBudget(6), lambda *a: None, tmp_path / "w1")

    class Killed(Exception):
        pass

    def die_at_5(step, total, stats):
        if step == 5:
            raise Killed

    interrupted = make(frames=2)
    with pytest.raises(Killed):
        interrupted.fit(dataset, FitBudget(6), die_at_5, tmp_path / "w2")
    assert (tmp_path / "w2" / "train_checkpoint.pt").exists()
    resumed = make(frames=2)
    resumed.fit(dataset, FitBudget(6), lambda *a: None, tmp_path / "w2")
    for p, q in zip(straight.net.parameters(), resumed.net.parameters(), strict=True):
        assert torch.equal(p, q)


def test_nan_loss_stops_with_the_step(tmp_path, monkeypatch):
    dataset = ensure_dataset(tmp_path, synthetic_config(), synthetic_collector, show_progress=False)
    monkeypatch.setattr(training, "multiview_npairs_loss", lambda e, r: e.sum() * float("nan"))
    with pytest.raises(TrainingError, match="at step 0"):
        make().fit(dataset, FitBudget(3), lambda *a: None, tmp_path / "w")


def test_training_lowers_the_loss(tmp_path):
    dataset = ensure_dataset(tmp_path, synthetic_config(episode_length=60), synthetic_collector,
                             show_progress=False)
    losses = []
    make(frames=2).fit(dataset, FitBudget(40), lambda s, t, st: losses.append(st["loss"]), tmp_path / "w")
    assert np.mean(losses[-5:]) < np.mean(losses[:5])


def test_the_heldout_loss_is_the_test_episodes_loss_in_eval_mode_and_changes_no_weight(tmp_path):
    """Every `heldout_every` steps: the n-pairs loss of `heldout_batches` fixed batches of TEST episodes, with
    the network in eval mode (BatchNorm's running statistics), computed here by hand from the same plans; the
    fitted weights are those of a fit without it, and the curve survives a kill."""
    from mftcn_bench.encoders.losses import multiview_npairs_loss
    from mftcn_bench.encoders.sampling import plan_batch

    dataset = ensure_dataset(tmp_path / "d", synthetic_config(test_episodes=2), synthetic_collector,
                             show_progress=False)
    plain = make(frames=2)
    plain_stats = plain.fit(dataset, FitBudget(6), lambda *a: None, tmp_path / "w1")
    assert "heldout_loss" not in plain_stats
    losses = []
    watched = make(frames=2, heldout_every=4, heldout_batches=3)
    stats = watched.fit(dataset, FitBudget(6), lambda s, t, st: losses.append(st["loss"]), tmp_path / "w2")
    for p, q in zip(plain.net.parameters(), watched.net.parameters(), strict=True):
        assert torch.equal(p, q)
    for p, q in zip(plain.net.buffers(), watched.net.buffers(), strict=True):  # BatchNorm's statistics too
        assert torch.equal(p, q)
    assert all(isinstance(v, float) for v in stats.values())  # the contract: summary statistics only
    curve = json.loads((tmp_path / "w2" / FIT_CURVE).read_text())  # the curve, for the run's record
    assert not (tmp_path / "w1" / FIT_CURVE).exists()
    assert curve["step"] == [4.0, 6.0]  # every 4 steps, and at the end
    assert curve["train_loss"] == pytest.approx([np.mean(losses[:4]), np.mean(losses[4:])])
    assert stats["heldout_loss"] == curve["heldout_loss"][-1]

    test = dataset.episodes("test")
    rng = np.random.default_rng([0, 1])  # the fit's seed, then the held-out stream
    plans = [plan_batch(rng, sorted(test), {i: dataset.episode_length(i) for i in test}, 4, 2, 2) for _ in range(3)]
    pool = EpisodePool(dataset, len(test), 0, rng, members=list(test))
    watched.net.eval()
    by_hand = []
    with torch.no_grad():
        for plan in plans:
            assert set(plan.episodes.tolist()) <= set(test)
            clips = gather_clips(pool, plan.episodes, plan.times, frames=2, stride=1)
            views, count = clips.shape[:2]
            flat = torch.from_numpy(clips.reshape(views * count, *clips.shape[2:])).permute(0, 1, 4, 2, 3)
            by_hand.append(float(multiview_npairs_loss(watched.net(flat).reshape(views, count, -1), 0.002)))
    assert stats["heldout_loss"] == pytest.approx(np.mean(by_hand), rel=1e-5)

    class Killed(Exception):
        pass

    def die_at_5(step, total, st):
        if step == 5:
            raise Killed

    with pytest.raises(Killed):
        make(frames=2, heldout_every=4, heldout_batches=3).fit(dataset, FitBudget(6), die_at_5, tmp_path / "w3")
    make(frames=2, heldout_every=4, heldout_batches=3).fit(dataset, FitBudget(6), lambda *a: None, tmp_path / "w3")
    assert json.loads((tmp_path / "w3" / FIT_CURVE).read_text())["heldout_loss"] == curve["heldout_loss"]


def test_spatial_softargmax_is_the_expected_position_under_a_softmax_over_the_map():
    from mftcn_bench.encoders.mftcn import spatial_softargmax

    maps = torch.randn(2, 3, 4, 5, dtype=torch.float64)
    out = spatial_softargmax(maps).numpy()
    for b in range(2):
        for c in range(3):
            p = np.exp(maps[b, c].numpy())
            p /= p.sum()
            rows, cols = np.meshgrid(np.linspace(-1, 1, 4), np.linspace(-1, 1, 5), indexing="ij")
            assert out[b, c] == pytest.approx((p * cols).sum()) and out[b, 3 + c] == pytest.approx((p * rows).sum())
    peak = torch.full((1, 1, 3, 3), -50.0)
    peak[0, 0, 2, 0] = 50.0  # bottom-left cell: x = -1, y = +1
    assert spatial_softargmax(peak)[0].tolist() == pytest.approx([-1.0, 1.0])


def test_the_head_candidates_keep_the_papers_head_by_default_and_change_only_what_they_name():
    default = make(frames=2, dim=4).net
    assert default.temporal.kernel_size == (2, 3, 3) and default.fc.in_features == 8  # MODEL's temporal_channels
    wide = MfTCNEncoder(EncoderSpec("t", "mftcn", "test", 2, 1, 4, {**MODEL, "temporal_kernel": 5,
                                                                     "spatial_pool": "mean+softargmax"}, TRAIN),
                        image_shape=(16, 24), seed=0)
    assert wide.net.temporal.kernel_size == (2, 5, 5) and wide.net.fc.in_features == 24
    clips = np.random.default_rng(0).integers(0, 255, (3, 2, 16, 24, 3), dtype=np.uint8)
    assert wide.embed(ClipBatch(clips)).shape == (3, 4)
    for bad in ({"temporal_kernel": 4}, {"spatial_pool": "max"}):
        with pytest.raises(Exception, match="temporal_kernel|spatial_pool"):
            MfTCNEncoder(EncoderSpec("t", "mftcn", "test", 2, 1, 4, {**MODEL, **bad}, TRAIN), (16, 24), 0)
