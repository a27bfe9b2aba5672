import numpy as np
import pytest

from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.encoders.mftcn import MfTCNEncoder
from mftcn_bench.encoders.streaming import StreamingEmbedder

SHAPE = (16, 24)
MODEL = {"adapter_channels": 8, "temporal_channels": 8,
         "base": {"name": "small-cnn", "channels": [8, 8], "kernels": [3, 3], "strides": [2, 2], "coords": True}}
TRAIN = {"steps": 1, "batch_timesteps": 4, "episodes_per_batch": 2, "alpha": 2, "lr": 1e-3,
         "weight_decay": 1e-6, "reg_lambda": 0.002, "episode_pool": 2, "pool_refresh_steps": 2,
         "checkpoint_every": 0, "max_seconds": 0.0}


def make(frames, stride):
    spec = EncoderSpec("t", "mftcn", "test", frames, stride, 8, MODEL, TRAIN)
    return MfTCNEncoder(spec, image_shape=SHAPE, seed=0)


def episode(rng, length):
    return rng.integers(0, 255, (length, *SHAPE, 3), dtype=np.uint8)


def count_calls(net, method):
    """Wrap `net.<method>` to record the batch size of each call; returns the list it appends to."""
    calls, original = [], getattr(net, method)

    def counting(batch):
        calls.append(len(batch))
        return original(batch)

    setattr(net, method, counting)
    return calls


@pytest.mark.parametrize("frames,stride,lookback", [(1, 1, 1), (5, 1, 5), (4, 4, 13), (5, 7, 29)])
def test_streaming_equals_episode_embedding_across_boundaries(one_torch_thread, frames, stride, lookback):
    encoder = make(frames, stride)
    assert encoder.info.lookback == lookback
    rng = np.random.default_rng(lookback)
    # env 0: episode A (17 frames) then B (23); env 1: C (31, longer than every lookback) then D (9)
    a, b, c, d = episode(rng, 17), episode(rng, 23), episode(rng, 31), episode(rng, 9)
    streams = [np.concatenate([a, b]), np.concatenate([c, d])]
    starts = np.zeros((40, 2), dtype=bool)
    starts[[0, 17], 0] = True
    starts[[0, 31], 1] = True
    expected = [np.concatenate([encoder.embed_episode(a), encoder.embed_episode(b)]),
                np.concatenate([encoder.embed_episode(c), encoder.embed_episode(d)])]
    streamer = encoder.streaming(num_envs=2)
    for t in range(40):
        out = streamer.push(np.stack([streams[0][t], streams[1][t]]), starts[t])
        assert out.shape == (2, 8) and out.dtype == np.float32
        for env in range(2):
            assert np.abs(out[env] - expected[env][t]).max() < 1e-5, (t, env)


def test_every_frame_costs_one_base_forward_whatever_the_lookback():
    encoder = make(5, 7)
    calls = count_calls(encoder.net, "frame_features")
    streamer = encoder.streaming(num_envs=3)
    frames = episode(np.random.default_rng(0), 3)
    streamer.push(frames, np.ones(3, bool))
    for _ in range(40):
        streamer.push(frames, np.zeros(3, bool))
    assert calls == [3] * 41


def test_an_env_must_start_an_episode_first():
    streamer = make(2, 1).streaming(num_envs=2)
    frames = episode(np.random.default_rng(0), 2)
    with pytest.raises(ValueError, match=r"environments \[1\] have not started"):
        streamer.push(frames, np.array([True, False]))
    with pytest.raises(ValueError, match="frames must be"):
        streamer.push(frames[:1], np.array([True, True]))
    streamer.push(frames, np.array([True, True]))
    streamer.reset()
    with pytest.raises(ValueError, match="have not started"):
        streamer.push(frames, np.array([False, True]))


def test_streaming_accepts_any_frame_head_network():
    encoder = make(3, 2)
    streamer = StreamingEmbedder(encoder.net, frames=3, stride=2, num_envs=1)
    frames = episode(np.random.default_rng(1), 6)
    out = np.concatenate([streamer.push(f[None], np.array([t == 0])) for t, f in enumerate(frames)])
    assert np.allclose(out, encoder.embed_episode(frames), atol=1e-5)


def test_observed_frames_enter_the_history_without_a_head_pass():
    encoder = make(5, 1)
    heads = count_calls(encoder.net, "head")
    streamer = encoder.streaming(num_envs=1)
    frames = episode(np.random.default_rng(2), 12)
    out = []
    for t, frame in enumerate(frames):  # embed every third frame only, as an action repeat of 3 does
        if t % 3 == 2:
            out.append(streamer.push(frame[None], np.array([t == 0])))
        else:
            streamer.observe(frame[None], np.array([t == 0]))
    assert len(heads) == 4
    assert np.allclose(np.concatenate(out), encoder.embed_episode(frames)[2::3], atol=1e-5)
