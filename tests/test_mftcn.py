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


BAR_LENGTH = 40  # frames per episode of the moving-bar data


def moving_bar_collector(config, index):
    """Two views of one bar sweeping across the image: view 0 a red bar at column c(t), view 1 a green bar at
    the mirrored column W-1-c(t). Each episode sweeps from near one edge to near the other (its own start,
    end and direction), so within an episode the column says the time step. What matches across the views is
    the bar's column mirrored: the frames of one moment differ in colour and in where the bar is, and an
    untrained network pairs them no better than chance."""
    height, width = int(config["height"]), int(config["width"])
    rng = np.random.default_rng([int(config["seed"]), index])
    start, end = rng.uniform(0.0, 0.15), rng.uniform(0.85, 1.0)
    s = np.linspace(start, end, BAR_LENGTH) if rng.random() < 0.5 else np.linspace(end, start, BAR_LENGTH)
    columns = np.round(s * (width - 1)).astype(int)
    frames = np.zeros((2, BAR_LENGTH, height, width, 3), dtype=np.uint8)
    for t, column in enumerate(columns):
        frames[0, t, :, column, 0] = 255
        frames[1, t, :, width - 1 - column, 1] = 255
    return {"frames": frames, "state": np.repeat(s[:, None], 4, axis=1),
            "action": np.zeros((BAR_LENGTH, 1), dtype=np.float32)}


def bar_retrieval(encoder, frames, every=4):
    """Of the times 1, 1 + every, ... of one episode [views, T, H, W, 3]: the fraction whose view-0 embedding
    (the anchor) has its largest inner product (the n-pairs loss's logit) with the view-1 embedding of the
    same time, among the view-1 embeddings of all those times."""
    times = np.arange(1, frames.shape[1], every)
    anchors, positives = (encoder.embed_episode(frames[v])[times] for v in (0, 1))
    return float(((anchors @ positives.T).argmax(1) == np.arange(len(times))).mean())


def test_training_aligns_the_views_of_a_held_out_episode_and_brings_the_loss_to_a_quarter_of_chance(
        tmp_path, one_torch_thread):
    """800 steps of the fit on the moving-bar data (4 train episodes, 1 test episode; one episode and 8 time
    steps a batch) take the training n-pairs loss from chance, log 8 = 2.08 (what equal logits give), to a
    mean over the last 20 steps below a quarter of it (measured 0.13-0.33 over network seeds 0-7), and align
    the HELD-OUT episode's views: among 10 of its times 4 frames apart, a view-0 embedding's largest logit is
    with the view-1 embedding of its own time for at least 6 of them (measured 8-10 of 10 over seeds 0-7; the
    same networks untrained: 1 of 10, chance). A loss with the wrong positives (views or times mismatched), no
    gradient, or a sign error fails it; so does a network that cannot tell where the bar is."""
    config = synthetic_config(name="moving-bar", train_episodes=4, test_episodes=1, episode_length=BAR_LENGTH)
    dataset = ensure_dataset(tmp_path / "d", config, moving_bar_collector, show_progress=False)
    [held_out] = dataset.episodes("test")
    frames = dataset.load(held_out).frames
    untrained = make(frames=2, batch_timesteps=8, episodes_per_batch=1, episode_pool=4, pool_refresh_steps=0,
                     checkpoint_every=0, lr=3e-3)
    assert bar_retrieval(untrained, frames) <= 0.3, "the data must not align without training"
    encoder = make(frames=2, batch_timesteps=8, episodes_per_batch=1, episode_pool=4, pool_refresh_steps=0,
                   checkpoint_every=0, lr=3e-3)
    losses = []
    encoder.fit(dataset, FitBudget(800), lambda s, t, st: losses.append(st["loss"]), tmp_path / "w")
    chance = np.log(8)
    assert abs(np.mean(losses[:5]) - chance) < 0.25, f"first losses {losses[:5]} are not at chance {chance:.3f}"
    assert np.mean(losses[-20:]) < 0.25 * chance, f"last 20 losses average {np.mean(losses[-20:]):.3f}"
    retrieved = bar_retrieval(encoder, frames)
    assert retrieved >= 0.6, f"held-out episode: {retrieved:.0%} of its times retrieved across the views"


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


def _paper_head_by_hand(net, features: np.ndarray) -> np.ndarray:
    """The mfTCN head written out in float64 from the network's weights, frame by frame: per frame the
    adapter (3x3 convolution with zero padding, BatchNorm with its running statistics, ReLU); then the 3D
    convolution as the sum over the clip's frames (oldest first) of 2D 3x3 convolutions with the kernel's
    slice for that frame, plus its bias, ReLU; the mean over the map's cells; the linear layer."""
    import torch.nn.functional as F

    def t(x):
        return torch.as_tensor(np.asarray(x), dtype=torch.float64)

    conv, bn = net.adapter[0], net.adapter[1]
    x = t(features)  # [B, n, C, h, w]
    adapted = []
    for f in range(x.shape[1]):
        y = F.conv2d(x[:, f], t(conv.weight.detach()), t(conv.bias.detach()), padding=1)
        y = (y - t(bn.running_mean)[:, None, None]) / torch.sqrt(t(bn.running_var)[:, None, None] + bn.eps)
        adapted.append(torch.relu(y * t(bn.weight.detach())[:, None, None] + t(bn.bias.detach())[:, None, None]))
    kernel = t(net.temporal.weight.detach())  # [out, in, n, 3, 3]
    phi = t(net.temporal.bias.detach())[None, :, None, None]
    for f, frame in enumerate(adapted):
        phi = phi + F.conv2d(frame, kernel[:, :, f], padding=1)
    pooled = torch.relu(phi).mean(dim=(2, 3))  # [B, out]
    return (pooled @ t(net.fc.weight.detach()).T + t(net.fc.bias.detach())).numpy()


def test_the_papers_head_on_the_10x10_map_of_a_160x160_frame_is_conv3d_relu_mean_linear(one_torch_thread):
    """mftcn5's own spec (the paper's head: adapter 128, 3D convolution 128 x (5 frames, 3, 3), spatial_pool
    "mean", embedding 32) on base features [B, 5, 112, 10, 10], the map the base gives a 160x160 frame at the
    spec's resize 1 (checked here on real frames; swingup-160's presets resize by 0.6 to a 6x6 map,
    tests/test_bases.py): the output is [B, 32] and equals the head written out by hand in float64 from the
    same weights (`_paper_head_by_hand`), with the adapter's BatchNorm given statistics of its own so that
    they count. Pins the frame order against the kernel's frame axis, the zero padding that keeps the 10x10
    map, the ReLU before the pooling, the mean over all 100 cells and the linear layer; a swapped frame
    order, a max pool, an unpadded (8x8) map or BatchNorm in training mode fails it."""
    from mftcn_bench.core import registry

    entry = registry.get("encoders", "mftcn5")
    encoder = MfTCNEncoder(entry.spec, image_shape=(160, 160), seed=0)
    net = encoder.net
    assert encoder.model_config.spatial_pool == "mean" and encoder.model_config.temporal_kernel == 3
    frames = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (5, 3, 160, 160), dtype=np.uint8))
    with torch.no_grad():
        assert net.base.net(frames).shape == (5, 112, 10, 10)  # eager: the map the head reads at 160x160
    rng = np.random.default_rng(1)
    bn = net.adapter[1]
    with torch.no_grad():  # statistics and an affine map of their own, as after a fit
        bn.running_mean.copy_(torch.from_numpy(rng.normal(0.0, 0.5, 128)))
        bn.running_var.copy_(torch.from_numpy(rng.uniform(0.5, 2.0, 128)))
        bn.weight.copy_(torch.from_numpy(rng.uniform(0.5, 1.5, 128)))
        bn.bias.copy_(torch.from_numpy(rng.normal(0.0, 0.2, 128)))
    features = rng.normal(0.0, 1.0, (2, 5, 112, 10, 10)).astype(np.float32)
    features[:, :, :, :3, :3] += 4.0  # content in one corner, where the padding is read: a spatial layout
    net.eval()
    with torch.no_grad():
        ours = net.head_on_base(torch.from_numpy(features)).numpy()
    assert ours.shape == (2, 32)
    expected = _paper_head_by_hand(net, features)
    assert np.abs(expected).max() > 0.05  # not a trivially small output
    error = float(np.abs(ours - expected).max())
    assert error < 1e-5, f"max |head - by hand| = {error:.2e}"
    # The by-hand head tells the frame order apart (the clip reversed gives another embedding).
    assert np.abs(_paper_head_by_hand(net, features[:, ::-1].copy()) - expected).max() > 1e-3
