import numpy as np
import pytest
import torch

from mftcn_bench.core import registry
from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.encoders.base import ClipBatch, Encoder, embed_episode
from mftcn_bench.encoders.baselines import PixelsCNNEncoder, RandomStateEncoder, TrueStateEncoder

CNN = {"channels": [8, 8], "kernels": [3, 3], "strides": [2, 2], "coords": True}


def clips(count, frames=1, seed=0, shape=(8, 12)):
    return np.random.default_rng(seed).integers(0, 255, (count, frames, *shape, 3), dtype=np.uint8)


def random_state(seed=0, dim=5, model=None):
    spec = EncoderSpec("random-state", "baseline", "test", 1, 1, dim, model or {"std": 1.0}, {"steps": 0})
    return RandomStateEncoder(spec, image_shape=(8, 12), seed=seed)


def true_state(dim=5, frames=1, noise=None, seed=0):
    model = {} if noise is None else {"noise_std": noise}
    spec = EncoderSpec("true-state", "baseline", "test", frames, 1, dim, model, {"steps": 0})
    return TrueStateEncoder(spec, image_shape=(8, 12), seed=seed)


def pixels(frames=1, seed=0, dim=6):
    spec = EncoderSpec("pixels-cnn", "baseline", "test", frames, 1, dim, CNN, {"steps": 0})
    return PixelsCNNEncoder(spec, image_shape=(8, 12), seed=seed)


@pytest.mark.parametrize("name", ["random-state", "true-state", "pixels-cnn", "pve", "shuffle-and-learn"])
def test_registered_spec_builds_its_encoder(name):
    entry = registry.get("encoders", name)
    encoder = entry.load()(entry.spec, image_shape=(48, 96), seed=0)
    assert isinstance(encoder, Encoder)
    assert encoder.info.embedding_dim == entry.spec.embedding_dim
    assert encoder.needs_fit == (name in ("pve", "shuffle-and-learn"))


def test_random_state_is_noise_fixed_per_clip_whatever_the_batch_order():
    encoder = random_state()
    batch = clips(6)
    out = encoder.embed(ClipBatch(batch))
    assert out.shape == (6, 5) and out.dtype == np.float32
    reordered = encoder.embed(ClipBatch(batch[::-1].copy()))
    assert np.array_equal(out[::-1], reordered)
    assert np.array_equal(out[2:3], encoder.embed(ClipBatch(batch[2:3])))
    assert len({tuple(row) for row in out}) == 6  # different clips, different noise
    assert not np.allclose(out, random_state(seed=1).embed(ClipBatch(batch)))


def test_random_state_streams_the_noise_it_embeds_and_two_views_differ():
    encoder, frames = random_state(), clips(3)[:, 0]
    state = np.zeros((3, 4))  # the same state for all: the noise must not follow it
    stream = encoder.streaming(3).push(frames, np.ones(3, bool), state)
    assert np.array_equal(stream, encoder.embed(ClipBatch(frames[:, None], state[:, None])))
    assert len({tuple(row) for row in stream}) == 3


def test_random_state_noise_is_standard_normal_scaled_by_std():
    out = random_state(dim=4, model={"std": 2.0}).embed(ClipBatch(clips(500, shape=(2, 2))))
    assert abs(out.mean()) < 0.2
    assert 1.8 < out.std() < 2.2


def test_random_state_rejects_unknown_model_keys():
    with pytest.raises(SpecError, match="unknown key.*'sigma'"):
        random_state(model={"sigma": 1.0})


def test_true_state_maps_cartpole_state_of_the_last_frame_to_probe_targets():
    state = np.array([[[9.0, 9.0, 9.0, 9.0], [0.5, np.pi / 2, 1.0, -2.0]],
                      [[9.0, 9.0, 9.0, 9.0], [-1.0, np.pi, 0.0, 3.0]]])
    out = true_state(frames=2).embed(ClipBatch(clips(2, frames=2), state))
    expected = np.array([[0.5, 1.0, 0.0, 1.0, -2.0], [-1.0, 0.0, -1.0, 0.0, 3.0]], dtype=np.float32)
    assert out.dtype == np.float32
    assert np.allclose(out, expected, atol=1e-6)


def test_true_state_passes_other_state_sizes_through():
    state = np.arange(12, dtype=np.float64).reshape(2, 2, 3)
    out = true_state(dim=3, frames=2).embed(ClipBatch(clips(2, frames=2), state))
    assert np.array_equal(out, np.array([[3, 4, 5], [9, 10, 11]], dtype=np.float32))
    with pytest.raises(SpecError, match="embedding_dim=3"):
        true_state(dim=5, frames=2).embed(ClipBatch(clips(2, frames=2), state))


def test_true_state_without_state_is_a_clear_error():
    with pytest.raises(BenchError, match="needs the simulator state"):
        true_state().embed(ClipBatch(clips(2)))


def test_true_state_through_episode_embedding_uses_each_frames_state():
    state = np.stack([np.linspace(0, 1, 7), np.zeros(7), np.zeros(7), np.arange(7.0)], axis=1)
    out = embed_episode(true_state(), clips(7)[:, 0], state)
    assert np.allclose(out[:, 0], np.linspace(0, 1, 7)) and np.allclose(out[:, 4], np.arange(7))
    assert np.allclose(out[:, 2], 1.0)  # cos 0


def test_true_state_noise_has_its_std_per_dimension_and_streams_as_it_embeds():
    rng = np.random.default_rng(0)
    state = rng.normal(size=(4000, 1, 4))
    std = [0.1, 0.0, 0.5, 1.0, 2.0]
    clean = true_state().embed(ClipBatch(clips(4000, shape=(1, 1)), state))
    noisy = true_state(noise=std).embed(ClipBatch(clips(4000, shape=(1, 1)), state))
    assert np.allclose((noisy - clean).std(axis=0), std, rtol=0.05, atol=1e-7)
    assert abs((noisy - clean).mean()) < 0.05
    encoder = true_state(noise=std)
    pushed = encoder.streaming(4000).push(None, np.ones(4000, bool), state[:, -1])
    assert np.array_equal(pushed, noisy)  # the same noise for the same state, batch or rollout
    assert not np.allclose(true_state(noise=std, seed=1).embed(ClipBatch(clips(4000, shape=(1, 1)), state)), noisy)
    assert np.array_equal(true_state(noise=[0.0] * 5).embed(ClipBatch(clips(4000, shape=(1, 1)), state)), clean)
    with pytest.raises(SpecError, match="one value per embedding dimension"):
        true_state(noise=[0.1, 0.2])
    with pytest.raises(SpecError, match="finite numbers >= 0"):
        true_state(noise=[0.1, -1, 0, 0, 0])


def test_pixels_cnn_is_an_untrained_seeded_network():
    a, b, c = pixels(seed=0), pixels(seed=0), pixels(seed=1)
    batch = ClipBatch(clips(3))
    out = a.embed(batch)
    assert out.shape == (3, 6) and out.dtype == np.float32
    assert not a.needs_fit
    assert np.array_equal(out, b.embed(batch))
    assert not np.allclose(out, c.embed(batch))


def test_pixels_cnn_episode_embedding_equals_each_clip_and_concatenates_frames():
    encoder = pixels(frames=2)
    frames = clips(9)[:, 0]
    fast = encoder.embed_episode(frames)
    for t in (0, 1, 8):
        clip = frames[[max(t - 1, 0), t]][None]
        assert np.allclose(fast[t], encoder.embed(ClipBatch(clip))[0], atol=1e-5)
    assert encoder.net.fc.in_features == 2 * encoder.net.base.out_channels


def test_pixels_cnn_net_is_trainable_and_saved(tmp_path):
    encoder = pixels()
    images = torch.from_numpy(clips(2)).permute(0, 1, 4, 2, 3)
    encoder.net(images).sum().backward()
    assert all(p.grad is not None for p in encoder.net.parameters())
    with torch.no_grad():
        encoder.net.fc.bias.add_(1.0)
    encoder.save(tmp_path / "m.pt")
    other = pixels()
    other.load(tmp_path / "m.pt")
    batch = ClipBatch(clips(2))
    assert np.array_equal(encoder.embed(batch), other.embed(batch))
