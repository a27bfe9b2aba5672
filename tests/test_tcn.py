import numpy as np
import pytest
import torch

from mftcn_bench.core.errors import SpecError
from mftcn_bench.core.registry import get
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_config
from mftcn_bench.encoders.base import ClipBatch, FitBudget, embed_episode
from mftcn_bench.encoders.tcn import (
    TCNEncoder,
    sample_triplets,
    spatial_soft_argmax,
    triplet_loss,
)

MODEL = {"conv_channels": [], "hidden": [], "temperature": 1.0, "learn_temperature": True,
         "base": {"name": "small-cnn", "channels": [8, 8], "kernels": [3, 3], "strides": [2, 1], "coords": False}}
TRAIN = {"loss": "npairs", "steps": 6, "batch_timesteps": 8, "episodes_per_batch": 2, "alpha": 2, "lr": 3e-3,
         "weight_decay": 1e-6, "reg_lambda": 0.002, "episode_pool": 3, "pool_refresh_steps": 0,
         "checkpoint_every": 0, "max_seconds": 0.0, "positive_radius": 2, "negative_margin": 6, "margin": 0.2}


def make(dim=8, shape=(16, 24), seed=0, model=(), **train):
    spec = EncoderSpec("t", "tcn", "test", 1, 1, dim, {**MODEL, **dict(model)}, {**TRAIN, **train})
    return TCNEncoder(spec, image_shape=shape, seed=seed)


def blob_collector(config, index):
    """A bright 4x4 square moving across a dark image: its position encodes (episode, t); the second
    view shows it mirrored left-right."""
    length, h, w = int(config["episode_length"]), int(config["height"]), int(config["width"])
    rng = np.random.default_rng([int(config["seed"]), index])
    xs = np.clip(np.cumsum(rng.normal(0, 0.6, length)) + w / 2, 0, w - 4).astype(int)
    ys = (h // 2 - 2 + np.round(3 * np.sin(np.arange(length) / 5 + index))).astype(int)
    frames = np.zeros((2, length, h, w, 3), dtype=np.uint8)
    for t in range(length):
        frames[0, t, ys[t]:ys[t] + 4, xs[t]:xs[t] + 4] = 255
    frames[1] = frames[0, :, :, ::-1]
    state = np.stack([xs, ys], axis=1).astype(np.float64)
    return {"frames": frames, "state": state, "action": np.zeros((length, 1), np.float32)}


def blob_dataset(path):
    config = synthetic_config(height=16, width=24, episode_length=60, train_episodes=3)
    return ensure_dataset(path, config, blob_collector, show_progress=False)


def test_soft_argmax_of_a_peak_is_its_coordinate():
    features = torch.zeros(1, 2, 5, 9)
    features[0, 0, 1, 6] = 50.0  # row 1 of 5 -> y = -0.5; column 6 of 9 -> x = 0.5
    features[0, 1, 4, 0] = 50.0  # bottom-left corner -> (-1, 1)
    out = spatial_soft_argmax(features)
    assert out.shape == (1, 4)
    assert torch.allclose(out[0], torch.tensor([0.5, -0.5, -1.0, 1.0]), atol=1e-6)


def test_soft_argmax_of_a_uniform_map_is_the_centre_and_softmax_is_per_channel():
    assert torch.allclose(spatial_soft_argmax(torch.full((2, 3, 4, 7), 3.0)), torch.zeros(2, 6), atol=1e-6)
    # two equal peaks: the expectation lies halfway; a channel's values never affect another channel
    features = torch.zeros(1, 2, 3, 3)
    features[0, 0, 0, 0] = features[0, 0, 0, 2] = 40.0
    features[0, 1] = torch.randn(3, 3) * 100
    assert torch.allclose(spatial_soft_argmax(features)[0, :2], torch.tensor([0.0, -1.0]), atol=1e-6)
    # hand-computed: [[0, ln 3]] in a 1x2 map -> p = (1/4, 3/4) -> x = -1/4 + 3/4 = 0.5, y = 0
    two = torch.tensor([[[[0.0, float(np.log(3.0))]]]])
    assert torch.allclose(spatial_soft_argmax(two), torch.tensor([[0.5, 0.0]]), atol=1e-6)
    # a higher temperature flattens the distribution toward the centre
    assert torch.allclose(spatial_soft_argmax(2 * two, temperature=2.0), torch.tensor([[0.5, 0.0]]), atol=1e-6)


def test_output_shapes_and_episode_embedding():
    encoder = make(dim=6)
    assert encoder.info.frames == 1 and encoder.info.embedding_dim == 6
    frames = np.random.default_rng(0).integers(0, 255, (12, 16, 24, 3), dtype=np.uint8)
    out = encoder.embed(ClipBatch(frames[:5, None]))
    assert out.shape == (5, 6) and out.dtype == np.float32
    assert np.allclose(embed_episode(encoder, frames)[:5], out, atol=1e-5)
    triplet = make(dim=6, loss="triplet").embed(ClipBatch(frames[:5, None]))
    assert np.allclose(np.linalg.norm(triplet, axis=1), 1.0, atol=1e-5)  # triplet mode: unit embeddings


def test_spec_errors_are_one_line():
    with pytest.raises(SpecError, match="loss must be one of npairs, triplet"):
        make(loss="contrastive")
    with pytest.raises(SpecError, match="bad \\[train\\] table"):
        make(positive_radius=2, bogus=1)
    with pytest.raises(SpecError, match="bad \\[model\\] table"):
        make(model={"bogus": 1})
    with pytest.raises(SpecError, match="frames must be 1"):
        TCNEncoder(EncoderSpec("t", "tcn", "test", 2, 1, 8, MODEL, TRAIN), (16, 24), 0)


def test_registered_spec_builds():
    entry = get("encoders", "tcn")
    encoder = entry.load()(entry.spec, image_shape=(48, 96), seed=0)
    assert encoder.model_config.base.name == "efficientnet-lite0" and encoder.tcn_train_config.loss == "npairs"
    assert encoder.frozen_base() is not None and encoder.model_config.conv_channels == [128, 128]
    assert encoder.tcn_train_config.positive_radius == 6 and encoder.tcn_train_config.negative_margin == 12


def test_triplet_sampler_structure():
    rng = np.random.default_rng(0)
    lengths = {3: 40, 5: 25, 8: 14}
    plan = sample_triplets(rng, [3, 5, 8], lengths, views=2, count=300, episodes_per_batch=3,
                           positive_radius=6, negative_margin=12)
    assert set(plan.episodes.tolist()) == {3, 5, 8} and set(plan.views.tolist()) == {0, 1}
    length = np.array([lengths[int(e)] for e in plan.episodes])
    for times in (plan.anchors, plan.positives, plan.negatives):
        assert (times >= 0).all() and (times < length).all()
    close = np.abs(plan.positives - plan.anchors)
    assert ((close >= 1) & (close <= 6)).all()
    assert (np.abs(plan.negatives - plan.anchors) > 12).all()
    assert close.max() == 6  # the whole radius is used


def test_triplet_loss_value():
    a = torch.tensor([[0.0, 0.0], [0.0, 0.0]])
    p = torch.tensor([[1.0, 0.0], [0.0, 0.1]])
    n = torch.tensor([[0.0, 1.0], [0.0, 2.0]])
    # row 0: 1 - 1 + 0.5 = 0.5; row 1: 0.01 - 4 + 0.5 < 0 -> 0
    assert torch.isclose(triplet_loss(a, p, n, margin=0.5), torch.tensor(0.25))


@pytest.mark.parametrize("loss", ["npairs", "triplet"])
def test_training_lowers_the_loss(one_torch_thread, tmp_path, loss):
    dataset = blob_dataset(tmp_path / "d")
    losses = []
    make(loss=loss).fit(dataset, FitBudget(40), lambda s, t, st: losses.append(st["loss"]), tmp_path / "w")
    assert len(losses) == 40
    assert np.mean(losses[-8:]) < np.mean(losses[:8])


def test_triplet_training_resumes_bitwise(tmp_path):
    dataset = blob_dataset(tmp_path / "d")
    straight = make(loss="triplet", checkpoint_every=2)
    straight.fit(dataset, FitBudget(5), lambda *a: None, tmp_path / "w1")

    class Killed(Exception):
        pass

    def die_at_3(step, total, stats):
        if step == 3:
            raise Killed

    with pytest.raises(Killed):
        make(loss="triplet", checkpoint_every=2).fit(dataset, FitBudget(5), die_at_3, tmp_path / "w2")
    resumed = make(loss="triplet", checkpoint_every=2)
    resumed.fit(dataset, FitBudget(5), lambda *a: None, tmp_path / "w2")
    for p, q in zip(straight.net.parameters(), resumed.net.parameters(), strict=True):
        assert torch.equal(p, q)


def test_save_load_roundtrip(tmp_path):
    a, b = make(seed=0), make(seed=1)
    frames = np.random.default_rng(0).integers(0, 255, (3, 1, 16, 24, 3), dtype=np.uint8)
    a.save(tmp_path / "m.pt")
    b.load(tmp_path / "m.pt")
    assert np.array_equal(a.embed(ClipBatch(frames)), b.embed(ClipBatch(frames)))
