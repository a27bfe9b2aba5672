import numpy as np
import pytest
import torch

from mftcn_bench.core.errors import DataError, SpecError
from mftcn_bench.core.registry import get
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config
from mftcn_bench.encoders.base import ClipBatch, FeatureCacheUser, FitBudget
from mftcn_bench.encoders.bases import FrozenBase
from mftcn_bench.encoders.feature_cache import ensure_feature_cache
from mftcn_bench.encoders.shuffle_and_learn import (
    ShuffleAndLearnEncoder,
    order_tuples,
    sample_five,
    sample_order_batch,
)
from mftcn_bench.encoders.training import EpisodePool

SMALL = {"name": "small-cnn", "channels": [8, 8], "kernels": [3, 3], "strides": [2, 2], "coords": True}
LITE0 = {"name": "efficientnet-lite0", "layer": 4}  # a shallow cut keeps the tests fast
TRAIN = {"steps": 6, "batch_size": 8, "lr": 3e-3, "weight_decay": 0.0, "camera_index": 0, "episode_pool": 3,
         "pool_refresh_steps": 0, "checkpoint_every": 2, "max_seconds": 0.0, "min_spacing": 1,
         "max_spacing": 6}


def make(seed=0, frames=1, dim=8, base=None, adapter=0, shape=(8, 12), **train):
    model = {"base": dict(base or SMALL), "adapter_channels": adapter, "mlp_hidden": 16}
    spec = EncoderSpec("shuffle-and-learn", "shuffle-and-learn", "test", frames, 1, dim, model,
                       {**TRAIN, **train})
    return ShuffleAndLearnEncoder(spec, image_shape=shape, seed=seed)


def test_five_frames_are_ordered_with_gaps_in_range():
    rng = np.random.default_rng(0)
    draws = np.stack([sample_five(rng, 60, 3, 7) for _ in range(300)])
    gaps = np.diff(draws, axis=1)
    assert draws.min() >= 0 and draws.max() < 60
    assert gaps.min() == 3 and gaps.max() == 7
    capped = np.stack([sample_five(rng, 21, 1, 100) for _ in range(300)])
    assert np.diff(capped, axis=1).max() == 5 and capped.max() <= 20
    with pytest.raises(DataError, match="cannot hold 5 frames"):
        sample_five(rng, 20, 5, 9)


def test_positives_are_ordered_negatives_are_not_and_batches_are_balanced():
    rng = np.random.default_rng(0)
    five = np.stack([sample_five(rng, 80, 2, 6) for _ in range(200)])
    times, labels = order_tuples(five, rng)
    assert times.shape == (400, 3) and labels.sum() == 200
    positives, negatives = times[labels == 1], times[labels == 0]
    assert (positives == five[:, [1, 2, 3]]).all()
    assert ((positives[:, 0] < positives[:, 1]) & (positives[:, 1] < positives[:, 2])).all()
    assert (negatives[:, [0, 2]] == five[:, [1, 3]]).all()  # same outer frames b, d
    outside = (negatives[:, 1] < negatives[:, 0]) | (negatives[:, 1] > negatives[:, 2])
    assert outside.all()
    before = negatives[:, 1] == five[:, 0]
    after = negatives[:, 1] == five[:, 4]
    assert (before | after).all() and 60 < before.sum() < 140


def test_order_batch_takes_frames_of_one_view_of_one_episode(tmp_path):
    dataset = ensure_dataset(tmp_path, synthetic_config(), synthetic_collector, show_progress=False)
    pool = EpisodePool(dataset, size=3, refresh_steps=0, rng=np.random.default_rng(0))
    frames, labels, episodes, times = sample_order_batch(pool, np.random.default_rng(1), 10, 1, 2, 5)
    assert frames.shape == (20, 3, 8, 12, 3) and labels.shape == (20,)
    values = frames[:, :, 0, 0, 0].astype(int)
    assert (values == 100 + 7 * episodes[:, None] + times).all()
    in_order = (values[:, 0] < values[:, 1]) & (values[:, 1] < values[:, 2])
    assert (in_order == (labels == 1)).all()


def test_embedding_is_the_trunk_on_the_last_frame(tmp_path):
    encoder = make()
    frames = np.random.default_rng(0).integers(0, 255, (5, 8, 12, 3), dtype=np.uint8)
    out = encoder.embed_episode(frames)
    assert out.shape == (5, 8) and out.dtype == np.float32
    assert np.allclose(encoder.embed(ClipBatch(frames[:, None])), out, atol=1e-5)
    with torch.no_grad():
        trunk = encoder.net(torch.from_numpy(frames).permute(0, 3, 1, 2)[:, None]).numpy()
    assert np.allclose(out, trunk, atol=1e-5)
    encoder.save(tmp_path / "m.pt")
    other = make(seed=1)
    assert not np.allclose(other.embed_episode(frames), out)
    other.load(tmp_path / "m.pt")
    assert np.array_equal(other.embed_episode(frames), out)


def test_spec_checks():
    with pytest.raises(SpecError, match="frames = 1"):
        make(frames=2)
    with pytest.raises(SpecError, match="min_spacing <= max_spacing"):
        make(min_spacing=4, max_spacing=2)
    with pytest.raises(SpecError, match="unknown key.*'spacing'"):
        make(spacing=3)
    with pytest.raises(SpecError, match="adapter_channels must be >= 0"):
        make(adapter=-1)


def test_the_default_spec_sits_on_the_frozen_base_and_declares_its_cache():
    entry = get("encoders", "shuffle-and-learn")
    encoder = entry.load()(entry.spec, image_shape=(48, 96), seed=0)
    assert isinstance(encoder, FeatureCacheUser) and isinstance(encoder.frozen_base(), FrozenBase)
    assert make().frozen_base() is None  # small-cnn trains end to end: nothing to cache


def ramp_collector(config, index):
    """Uniform frames whose brightness rises 6 levels a frame: order is visible, but only by comparing."""
    length, h, w = int(config["episode_length"]), int(config["height"]), int(config["width"])
    brightness = (np.arange(length) * 6 + index * 3) % 256
    frames = np.broadcast_to(brightness.astype(np.uint8)[None, :, None, None, None], (2, length, h, w, 3))
    action = np.zeros((length, 1), np.float32)
    return {"frames": frames.copy(), "state": np.zeros((length, 4)), "action": action}


def test_training_lowers_the_order_loss(tmp_path):
    dataset = ensure_dataset(tmp_path, synthetic_config(), ramp_collector, show_progress=False)
    losses = []
    make(batch_size=16, lr=1e-2).fit(dataset, FitBudget(60), lambda s, n, st: losses.append(st["loss"]),
                                     tmp_path / "w")
    assert np.mean(losses[:10]) > 0.68  # chance: log 2
    assert np.mean(losses[-10:]) < 0.5


def noisy_ramp_collector(config, index):
    """The ramp with pixel noise, so that a base's features vary within a frame."""
    arrays = ramp_collector(config, index)
    noise = np.random.default_rng(index).integers(0, 40, arrays["frames"].shape, dtype=np.uint8)
    arrays["frames"] = arrays["frames"] // 2 + noise
    return arrays


def test_training_on_the_cache_equals_training_on_frames_and_streams_as_it_embeds(tmp_path):
    config = synthetic_config(height=16, width=24, episode_length=40)
    data = ensure_dataset(tmp_path / "d", config, noisy_ramp_collector, show_progress=False)
    on_frames, on_cache = (make(base=LITE0, adapter=8, shape=(16, 24), lr=1e-3) for _ in range(2))
    base = on_cache.frozen_base()
    on_cache.use_feature_cache(ensure_feature_cache(tmp_path / "f", data, base, base.identity(),
                                                    show_progress=False))
    losses_frames, losses_cache = [], []
    on_frames.fit(data, FitBudget(4), lambda s, t, st: losses_frames.append(st["loss"]), tmp_path / "w1")
    on_cache.fit(data, FitBudget(4), lambda s, t, st: losses_cache.append(st["loss"]), tmp_path / "w2")
    assert np.allclose(losses_frames, losses_cache, atol=1e-5)
    frames = data.load(data.episodes("test")[0]).frames[0]
    cached = on_cache.embed_episode(frames)
    assert np.allclose(on_frames.embed_episode(frames), cached, atol=1e-4)  # the base batched differently
    assert not any(p.requires_grad for p in base.parameters())
    stream = on_cache.streaming(1)
    for t in range(len(frames)):
        assert np.allclose(stream.push(frames[t:t + 1], np.array([t == 0]))[0], cached[t], atol=1e-5)
