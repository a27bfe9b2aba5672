"""The pretrained bases, the per-frame feature cache, and heads trained on it."""

import json

import numpy as np
import pytest
import torch

from mftcn_bench.core.errors import DataError, SpecError
from mftcn_bench.core.registry import get
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config
from mftcn_bench.encoders.base import FeatureCacheUser, FitBudget, embed_episode
from mftcn_bench.encoders.bases import BaseConfig, FrozenBase, build_base, lite0_weights_path, to_unit_range
from mftcn_bench.encoders.feature_cache import FeatureCache, ensure_feature_cache
from mftcn_bench.encoders.frozen_features import FrozenFeaturesEncoder
from mftcn_bench.encoders.mftcn import MfTCNEncoder

LITE0 = {"name": "efficientnet-lite0", "layer": 4}  # a shallow cut keeps the tests fast
TRAIN = {"steps": 4, "batch_timesteps": 4, "episodes_per_batch": 2, "alpha": 2, "lr": 1e-3,
         "weight_decay": 1e-6, "reg_lambda": 0.002, "episode_pool": 3, "pool_refresh_steps": 2,
         "checkpoint_every": 0, "max_seconds": 0.0}


def mftcn(frames=2, base=None, seed=0, shape=(16, 24)):
    model = {"adapter_channels": 8, "temporal_channels": 8, "base": dict(base or LITE0)}
    spec = EncoderSpec("t", "mftcn", "test", frames, 1, 8, model, TRAIN)
    return MfTCNEncoder(spec, image_shape=shape, seed=seed)


def dataset(tmp_path, **changes):
    config = synthetic_config(height=16, width=24, episode_length=30, **changes)
    return ensure_dataset(tmp_path / "data", config, synthetic_collector, show_progress=False)


def noisy_dataset(tmp_path):
    """Synthetic frames with noise, so that a base's features vary within a frame."""
    def collector(config, index):
        arrays = synthetic_collector(config, index)
        rng = np.random.default_rng(index)
        noise = rng.integers(0, 60, arrays["frames"].shape, dtype=np.uint8)
        arrays["frames"] = arrays["frames"] // 2 + noise
        return arrays

    config = synthetic_config(height=16, width=24, episode_length=30)
    return ensure_dataset(tmp_path / "noisy", config, collector, show_progress=False)


def test_lite0_features_equal_the_reference_implementation():
    from efficientnet_lite_pytorch import EfficientNet

    reference = EfficientNet.from_pretrained("efficientnet-lite0", weights_path=str(lite0_weights_path())).eval()
    base = build_base(BaseConfig(name="efficientnet-lite0", layer=10, engine="torch"))
    images = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (2, 3, 48, 96), dtype=np.uint8))
    with torch.no_grad():
        x = reference._swish(reference._bn0(reference._conv_stem(to_unit_range(images))))
        for block in reference._blocks[:11]:
            x = block(x)
        ours = base(images)
    assert ours.shape == (2, 112, 3, 6)
    assert torch.allclose(ours, x, atol=1e-5)


def _reference_block_output(reference, scaled: torch.Tensor, layer: int) -> torch.Tensor:
    """The output of block `layer` of the reference package's own forward pass (`extract_features`: its stem,
    then its blocks in order), caught by a hook, on input already scaled."""
    caught = []
    hook = reference._blocks[layer].register_forward_hook(lambda module, args, out: caught.append(out))
    try:
        with torch.no_grad():
            reference.extract_features(scaled)
    finally:
        hook.remove()
    return caught[0]


@pytest.mark.parametrize("shape,resize,engine,grid", [((160, 160), 1.0, "torch", (10, 10)),
                                                      ((160, 160), 1.0, "onnxruntime", (10, 10)),
                                                      ((160, 160), 0.6, "torch", (6, 6)),
                                                      ((48, 96), 1.0, "torch", (3, 6)),
                                                      ((84, 84), 1.0, "torch", (6, 6)),
                                                      ((84, 84), 1.0, "onnxruntime", (6, 6))])
def test_lite0_base_is_the_reference_network_cut_after_block_10_on_frames_scaled_by_hand(shape, resize, engine, grid):
    """The frozen base of the mfTCN specs (layer 10) against an independent reference: the
    `efficientnet_lite_pytorch` network with the installed ImageNet weights, run by its own forward pass on
    uint8 frames scaled BY HAND to [-1, 1] (x * 2 / 255 - 1, bases.py's documented preprocessing; resized
    bilinearly to the scaled size first when `resize` is not 1), read after block 10. Pins the scaling, the
    cut (block 10 of 0-15: 112 channels, a 10x10 map at 160x160, 6x6 after the 0.6 resize of swingup-160,
    3x6 at 96x48), the resize and both engines. The reference pads as TensorFlow's "SAME" for the size it is
    built for (the scaled frame's): at 84x84 a halving is odd (21 -> 11), where the package's 224-pixel padding
    gives a 5x5 map. So that the comparison can tell, a [0, 1] input, ImageNet's mean/std normalisation, a cut
    one block early (block 9 has the same 112 channels) and the padding of 224-pixel inputs each miss it."""
    from efficientnet_lite_pytorch import EfficientNet

    scaled_size = (round(shape[0] * resize), round(shape[1] * resize))
    reference = EfficientNet.from_pretrained("efficientnet-lite0", weights_path=str(lite0_weights_path()),
                                             image_size=scaled_size).eval()
    base = build_base(BaseConfig(name="efficientnet-lite0", layer=10, resize=resize, engine=engine))
    images = torch.from_numpy(np.random.default_rng(3).integers(0, 256, (2, 3, *shape), dtype=np.uint8))
    pixels = images.numpy().astype(np.float64)

    def reference_on(scaled: np.ndarray, layer: int = 10) -> torch.Tensor:
        x = torch.from_numpy(scaled).float()
        if resize != 1.0:
            size = (round(shape[0] * resize), round(shape[1] * resize))
            x = torch.nn.functional.interpolate(x, size=size, mode="bilinear", align_corners=False)
        return _reference_block_output(reference, x, layer)

    expected = reference_on(pixels * 2.0 / 255.0 - 1.0)
    ours = base(images)
    assert ours.shape == (2, 112, *grid) == expected.shape
    # float32 through 11 blocks, features of order 10: the by-hand scaling is rounded apart from the wrapper's
    tolerance = 1e-4
    error = float((ours - expected).abs().max())
    assert error < tolerance, f"max |base - reference| = {error:.2e}"
    mean = np.array([0.485, 0.456, 0.406])[None, :, None, None]
    std = np.array([0.229, 0.224, 0.225])[None, :, None, None]
    for wrong in (reference_on(pixels / 255.0), reference_on((pixels / 255.0 - mean) / std),
                  reference_on(pixels * 2.0 / 255.0 - 1.0, layer=9)):
        assert float((wrong - expected).abs().max()) > 1000 * tolerance
    reference = EfficientNet.from_pretrained("efficientnet-lite0", weights_path=str(lite0_weights_path())).eval()
    padded_for_224 = reference_on(pixels * 2.0 / 255.0 - 1.0)
    if shape == (84, 84):
        assert padded_for_224.shape[-2:] == (5, 5)
    else:  # sizes whose halvings are even, as 224's: that padding is right there
        assert float((padded_for_224 - expected).abs().max()) < tolerance


@pytest.mark.parametrize("shape", [(48, 96), (160, 160)])
def test_the_onnxruntime_engine_gives_the_eager_features_within_1e_4(shape):
    """The fast path of the frozen base (ONNX Runtime) against eager PyTorch at both task sizes, at the batch
    sizes a rollout and a cache build use (one session per input size, any batch size)."""
    eager = build_base(BaseConfig(name="efficientnet-lite0", layer=10, engine="torch"))
    fast = build_base(BaseConfig(name="efficientnet-lite0", layer=10))
    assert fast.config.engine == "onnxruntime", "the default engine"
    rng = np.random.default_rng(1)
    for batch in (1, 8, 5):
        images = torch.from_numpy(rng.integers(0, 256, (batch, 3, *shape), dtype=np.uint8))
        expected, got = eager(images), fast(images)
        assert got.shape == expected.shape and got.dtype == torch.float32
        assert float((got - expected).abs().max()) < 1e-4
    assert len(fast._onnxruntime._sessions) == 1, "one exported graph per input size, the batch size free"
    assert fast.identity() != eager.identity(), "the engine is part of the base's identity"


def test_an_onnxruntime_base_survives_a_copy():
    """A copy (a sweep's worker, a deep copy) rebuilds its sessions instead of carrying them."""
    import copy

    fast = build_base(BaseConfig(**LITE0))
    images = torch.from_numpy(np.random.default_rng(2).integers(0, 256, (2, 3, 16, 24), dtype=np.uint8))
    first = fast(images)
    clone = copy.deepcopy(fast)
    assert clone._onnxruntime._sessions == {} and torch.equal(clone(images), first)


def test_a_frozen_base_stays_frozen_and_names_its_weights():
    base = build_base(BaseConfig(**LITE0))
    assert isinstance(base, FrozenBase) and base.out_channels == 40
    base.train()
    assert not base.training and not base.net.training
    assert all(not p.requires_grad for p in base.parameters())
    identity = base.identity()
    assert len(identity["weights_sha256"]) == 64 and identity["base"]["layer"] == 4
    assert build_base(BaseConfig(**{**LITE0, "layer": 5})).identity() != identity
    small = build_base(BaseConfig(name="small-cnn"))
    assert not isinstance(small, FrozenBase) and any(p.requires_grad for p in small.parameters())


def test_base_config_errors_are_one_line():
    with pytest.raises(SpecError, match="name must be one of efficientnet-lite0, inception-v3, small-cnn"):
        BaseConfig(name="resnet")
    with pytest.raises(SpecError, match="layer must be a block of efficientnet-lite0, 0-15"):
        BaseConfig(layer=16)
    with pytest.raises(SpecError, match="engine must be one of torch, onnxruntime; got 'tensorrt'"):
        BaseConfig(engine="tensorrt")
    with pytest.raises(SpecError, match="bad \\[model.base\\] table: unknown key"):
        mftcn(base={"name": "efficientnet-lite0", "cut": 3})


def test_feature_cache_holds_every_frame_of_every_view(tmp_path):
    data = noisy_dataset(tmp_path)
    encoder = mftcn()
    base = encoder.frozen_base()
    cache = ensure_feature_cache(tmp_path / "features", data, base, base.identity(), show_progress=False)
    assert isinstance(encoder, FeatureCacheUser)
    episode = data.load(data.episodes("test")[0])
    features = cache.load(episode.index)
    assert features.shape == (2, 30, 40, 2, 3) and features.dtype == np.float32
    with torch.no_grad():
        direct = base(torch.from_numpy(episode.frames[1]).permute(0, 3, 1, 2)).numpy()
    assert np.array_equal(features[1], direct)
    assert np.array_equal(cache.lookup(episode.frames[1]), direct)
    assert cache.lookup(episode.frames[1][::-1].copy()) is None
    assert cache.size_bytes > 0 and cache.summary()["frames"] == 4 * 2 * 30
    again = ensure_feature_cache(tmp_path / "features", data, base, base.identity(), show_progress=False)
    assert again.root == cache.root  # found, not rebuilt
    other = build_base(BaseConfig(**{**LITE0, "layer": 3}))
    assert ensure_feature_cache(tmp_path / "features", data, other, other.identity(),
                                show_progress=False).root != cache.root


def test_a_corrupted_cache_file_is_refused_and_a_killed_build_resumes(tmp_path):
    data = dataset(tmp_path)
    base = build_base(BaseConfig(**LITE0))
    cache = ensure_feature_cache(tmp_path / "f", data, base, base.identity(), show_progress=False)
    (cache.root / "ep00000.npy").write_bytes(b"junk")
    with pytest.raises(DataError, match="does not match its checksum"):
        FeatureCache(cache.root).load(0)
    # A build killed after two episodes: the manifest is missing, progress lists what was done.
    manifest = json.loads((cache.root / "manifest.json").read_text())
    (cache.root / "manifest.json").unlink()
    kept = [e for e in manifest["episodes"] if e["episode"] in (1, 2)]
    (cache.root / "progress.json").write_text(json.dumps(kept))
    stamps = {e["file"]: (cache.root / e["file"]).stat().st_mtime_ns for e in kept}
    rebuilt = ensure_feature_cache(tmp_path / "f", data, base, base.identity(), show_progress=False)
    assert {f: (rebuilt.root / f).stat().st_mtime_ns for f in stamps} == stamps  # not recomputed
    assert rebuilt.load(0).shape[1] == 30 and not (rebuilt.root / "progress.json").exists()


def test_training_on_the_cache_equals_training_on_frames(tmp_path):
    data = noisy_dataset(tmp_path)
    on_frames, on_cache = mftcn(), mftcn()
    base = on_cache.frozen_base()
    on_cache.use_feature_cache(ensure_feature_cache(tmp_path / "f", data, base, base.identity(),
                                                    show_progress=False))
    losses_frames, losses_cache = [], []
    on_frames.fit(data, FitBudget(4), lambda s, t, st: losses_frames.append(st["loss"]), tmp_path / "w1")
    on_cache.fit(data, FitBudget(4), lambda s, t, st: losses_cache.append(st["loss"]), tmp_path / "w2")
    assert np.allclose(losses_frames, losses_cache, atol=1e-5)
    frames = data.load(data.episodes("test")[0]).frames[0]
    assert np.allclose(on_frames.embed_episode(frames), on_cache.embed_episode(frames), atol=1e-5)


def test_cached_episode_embedding_equals_batch_and_streaming_embedding(tmp_path):
    data = noisy_dataset(tmp_path)
    encoder = mftcn(frames=3)
    base = encoder.frozen_base()
    encoder.use_feature_cache(ensure_feature_cache(tmp_path / "f", data, base, base.identity(),
                                                   show_progress=False))
    frames = data.load(data.episodes("test")[0]).frames[0]
    cached = encoder.embed_episode(frames)
    plain = mftcn(frames=3)  # the same seed: the same weights, no cache
    assert np.allclose(cached, plain.embed_episode(frames), atol=1e-5)
    stream = encoder.streaming(1)
    for t in range(len(frames)):
        out = stream.push(frames[t:t + 1], np.array([t == 0]))
        assert np.allclose(out[0], cached[t], atol=1e-5)


def test_frozen_features_encoder_is_the_spatial_mean():
    entry = get("encoders", "lite0-features")
    encoder = entry.load()(entry.spec, image_shape=(16, 24), seed=0)
    assert encoder.needs_fit is False and encoder.info.embedding_dim == 112
    frames = np.random.default_rng(0).integers(0, 255, (5, 16, 24, 3), dtype=np.uint8)
    with torch.no_grad():
        expected = encoder.frozen_base()(torch.from_numpy(frames).permute(0, 3, 1, 2)).mean(dim=(2, 3))
    assert np.allclose(embed_episode(encoder, frames), expected.numpy(), atol=1e-5)
    spec = EncoderSpec("f", "frozen-base", "test", 1, 1, 32, {"base": {"name": "efficientnet-lite0"}}, {})
    with pytest.raises(SpecError, match="embedding_dim 112"):
        FrozenFeaturesEncoder(spec, (16, 24), 0)
    spec = EncoderSpec("f", "frozen-base", "test", 1, 1, 64, {"base": {"name": "small-cnn"}}, {})
    with pytest.raises(SpecError, match="needs a frozen pretrained base"):
        FrozenFeaturesEncoder(spec, (16, 24), 0)


def test_small_cnn_ablation_trains_its_base(tmp_path):
    data = dataset(tmp_path)
    encoder = mftcn(base={"name": "small-cnn", "channels": [8, 8], "kernels": [3, 3], "strides": [2, 2]})
    assert encoder.frozen_base() is None
    before = [p.detach().clone() for p in encoder.net.base.parameters()]
    encoder.fit(data, FitBudget(2), lambda *a: None, tmp_path / "w")
    assert any(not torch.equal(a, b) for a, b in zip(before, encoder.net.base.parameters(), strict=True))


def test_runs_share_one_feature_cache_and_record_it(tmp_path, monkeypatch):
    from mftcn_bench.cli import main
    from mftcn_bench.results.store import ResultStore

    monkeypatch.setattr("mftcn_bench.tasks.probe.collect_episode", synthetic_collector)
    task = ["--task", "cartpole-probe", "--preset", "smoke", "--no-progress", "--home", str(tmp_path / "home"),
            "--set", "task.dataset.episode_length=30", "--set", "task.dataset.train_episodes=3",
            "--set", "task.dataset.test_episodes=1", "--set", "task.dataset.height=16",
            "--set", "task.dataset.width=24", "--set", "task.probe.epochs=3", "--set", "task.probe.hidden=[8]"]
    tiny = ["--set", "encoder.model.adapter_channels=8", "--set", "encoder.model.temporal_channels=8",
            "--set", "encoder.train.steps=2", "--set", "encoder.train.batch_timesteps=4",
            "--set", "encoder.train.episodes_per_batch=2", "--set", "encoder.train.alpha=2",
            "--set", "encoder.train.episode_pool=2", "--set", "encoder.train.checkpoint_every=0"]
    assert main(["run", "--encoder", "mftcn2", *task, *tiny]) == 0
    assert main(["run", "--encoder", "lite0-features", *task]) == 0
    assert main(["run", "--encoder", "mftcn2", *task, *tiny, "--set", "encoder.model.base.layer=9"]) == 0
    records = {(r.encoder, r.config["fit"]["feature_cache"]["base"]["base"]["layer"]): r
               for r in ResultStore(tmp_path / "home" / "results.sqlite").query()}
    caches = {key: r.config["fit"]["feature_cache"] for key, r in records.items()}
    assert caches[("mftcn2", 10)]["path"] == caches[("lite0-features", 10)]["path"]  # built once, shared
    assert caches[("mftcn2", 9)]["path"] != caches[("mftcn2", 10)]["path"]
    assert len(list((tmp_path / "home" / "features").iterdir())) == 2 + 2  # two caches and their locks
    assert caches[("mftcn2", 10)]["bytes"] > 0 and caches[("mftcn2", 10)]["frames"] == 4 * 2 * 30
    encoders = sorted(p.name for p in (tmp_path / "home" / "encoders").iterdir() if p.is_dir())
    assert len(encoders) == 2  # the base's layer is part of the trained encoder's key


def test_to_unit_range_leaves_a_float_input_as_it_was():
    from mftcn_bench.encoders.bases import to_unit_range

    frames = torch.full((1, 3, 2, 2), 255.0)
    out = to_unit_range(frames)
    assert torch.equal(frames, torch.full((1, 3, 2, 2), 255.0)) and torch.allclose(out, torch.ones_like(out))
    assert torch.equal(to_unit_range(torch.zeros(1, 3, 1, 1, dtype=torch.uint8)), -torch.ones(1, 3, 1, 1))


class OwnBackbone:
    """A plugin's own frozen backbone, no `FrozenBase`: a fixed average pool, named by its window."""

    def __init__(self, window: int) -> None:
        self.window = window

    def identity(self) -> dict:
        return {"backbone": "avgpool", "window": self.window}

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.avg_pool2d(images.float(), self.window)


class OwnBackboneEncoder:
    """Only what the feature cache needs of an encoder: `FeatureCacheUser` over `OwnBackbone`."""

    def __init__(self, base) -> None:
        self.base, self.cache = base, None
        self.info = type("Info", (), {"name": "plugin"})()

    def frozen_base(self):
        return self.base

    def use_feature_cache(self, cache) -> None:
        self.cache = cache


def test_a_plugins_own_frozen_backbone_gets_a_shared_cache_keyed_by_its_identity(tmp_path):
    from mftcn_bench.core.home import BenchHome
    from mftcn_bench.encoders.base import FrozenFrameBase
    from mftcn_bench.run.artifacts import attach_feature_cache

    data, home = dataset(tmp_path), BenchHome(tmp_path / "home")
    first, again, other = (OwnBackboneEncoder(OwnBackbone(w)) for w in (4, 4, 8))
    assert isinstance(first.base, FrozenFrameBase) and isinstance(first, FeatureCacheUser)
    records = [attach_feature_cache(encoder, data, home, show_progress=False) for encoder in (first, again, other)]
    assert records[0]["base"] == {"backbone": "avgpool", "window": 4}
    assert records[0]["path"] == records[1]["path"] != records[2]["path"]  # shared; another identity, another cache
    episode = data.load(data.episodes("train")[0])
    view = episode.frames[1]  # [T, H, W, 3]
    expected = OwnBackbone(4)(torch.from_numpy(view).permute(0, 3, 1, 2)).numpy()
    np.testing.assert_array_equal(first.cache.lookup(view), expected)
    assert first.cache.load(data.episodes("train")[0]).shape == (2, 30, 3, 4, 6)


def test_a_frozen_base_that_is_no_frozen_frame_base_is_refused_in_one_line(tmp_path):
    from mftcn_bench.core.errors import BenchError
    from mftcn_bench.run.construct import frozen_base_of

    with pytest.raises(BenchError, match=r"^encoder 'plugin': frozen_base\(\) returned a Linear, which is no "
                                         r"FrozenFrameBase \(identity\(\) and a call"):
        frozen_base_of(OwnBackboneEncoder(torch.nn.Linear(2, 2)))
