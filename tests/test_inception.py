import numpy as np
import pytest
import torch

from mftcn_bench.core.errors import BenchError, SpecError
from mftcn_bench.core.registry import get
from mftcn_bench.core.specs import EncoderSpec
from mftcn_bench.encoders.base import ClipBatch, embed_episode
from mftcn_bench.encoders.bases import BaseConfig, InceptionV3Base
from mftcn_bench.encoders.frozen_features import FrozenFeaturesEncoder as InceptionEncoder
from mftcn_bench.encoders.inception import InceptionV3ToMixed5d

# Shapes of torchvision's Inception3 (torchvision/models/inception.py) for a sample of entries.
TORCHVISION_SHAPES = {
    "Conv2d_1a_3x3.conv.weight": (32, 3, 3, 3),
    "Conv2d_2b_3x3.bn.running_var": (64,),
    "Conv2d_3b_1x1.conv.weight": (80, 64, 1, 1),
    "Conv2d_4a_3x3.conv.weight": (192, 80, 3, 3),
    "Mixed_5b.branch5x5_2.conv.weight": (64, 48, 5, 5),
    "Mixed_5b.branch_pool.conv.weight": (32, 192, 1, 1),
    "Mixed_5c.branch_pool.conv.weight": (64, 256, 1, 1),
    "Mixed_5d.branch3x3dbl_1.conv.weight": (64, 288, 1, 1),
    "Mixed_5d.branch3x3dbl_3.bn.weight": (96,),
}


def spec(weights="", input_size=75, engine="torch", **changes):
    """Eager PyTorch by default: these tests hold the network to torchvision's; the engine has its own test."""
    data = {"family": "frozen-base", "description": "test", "frames": 1, "stride": 1, "embedding_dim": 288,
            "model": {"base": {"name": "inception-v3", "weights": str(weights), "input_size": input_size,
                               "engine": engine}},
            "train": {}}
    data.update(changes)
    return EncoderSpec.from_dict("inception", data)


def perturbed_module(seed=0):
    torch.manual_seed(seed)
    module = InceptionV3ToMixed5d()
    with torch.no_grad():
        for name, tensor in module.state_dict().items():
            if name.endswith("num_batches_tracked"):
                continue
            if name.endswith("running_var"):
                tensor.copy_(torch.rand_like(tensor) + 0.5)
            else:
                tensor.add_(torch.randn_like(tensor) * 0.1)
    return module.eval()


def torchvision_file(tmp_path, module):
    """A state_dict laid out as torchvision's inception_v3 file: our entries plus later blocks and heads."""
    state = dict(module.state_dict())
    state["Mixed_6a.branch3x3.conv.weight"] = torch.randn(384, 288, 3, 3)
    state["AuxLogits.conv0.conv.weight"] = torch.randn(128, 768, 1, 1)
    state["AuxLogits.fc.weight"] = torch.randn(1000, 768)
    state["fc.weight"] = torch.randn(1000, 2048)
    state["fc.bias"] = torch.randn(1000)
    path = tmp_path / "inception_v3_google-0cc3c7bd.pth"
    torch.save(state, path)
    return path


def test_module_names_and_shapes_are_torchvisions():
    state = InceptionV3ToMixed5d().state_dict()
    assert len(state) == 26 * 6  # 26 BasicConv2d: conv.weight + 5 BatchNorm entries each
    for name, shape in TORCHVISION_SHAPES.items():
        assert tuple(state[name].shape) == shape
    bn = InceptionV3ToMixed5d().Conv2d_1a_3x3.bn
    assert bn.eps == 0.001 and InceptionV3ToMixed5d().Conv2d_1a_3x3.conv.bias is None
    assert InceptionV3ToMixed5d()(torch.zeros(1, 3, 299, 299)).shape == (1, 288, 35, 35)


def test_loads_a_torchvision_file_and_ignores_the_rest(one_torch_thread, tmp_path):
    module = perturbed_module()
    encoder = InceptionEncoder(spec(torchvision_file(tmp_path, module)), image_shape=(24, 40), seed=0)
    assert encoder.needs_fit is False and encoder.info.embedding_dim == 288
    frames = np.random.default_rng(0).integers(0, 255, (5, 24, 40, 3), dtype=np.uint8)
    out = encoder.embed(ClipBatch(frames[:, None]))
    assert out.shape == (5, 288) and out.dtype == np.float32
    images = torch.from_numpy(frames).permute(0, 3, 1, 2).float()
    resized = torch.nn.functional.interpolate(images / 127.5 - 1, size=(75, 75), mode="bilinear",
                                              align_corners=False)
    with torch.no_grad():
        expected = module(resized).mean(dim=(2, 3)).numpy()
    assert np.allclose(out, expected, atol=1e-5)
    other = InceptionEncoder(spec(torchvision_file(tmp_path, perturbed_module(seed=1))), (24, 40), 0)
    assert not np.allclose(other.embed(ClipBatch(frames[:, None])), out, atol=1e-3)
    assert np.allclose(embed_episode(encoder, frames), out, atol=1e-5)


def test_preprocessing_equals_torchvision_normalize_then_transform_input(tmp_path):
    encoder = InceptionEncoder(spec(torchvision_file(tmp_path, InceptionV3ToMixed5d())), (24, 40), 0)
    images = torch.randint(0, 256, (2, 3, 24, 40), dtype=torch.uint8)
    mean, std = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])
    x = (images.float() / 255 - mean.view(1, 3, 1, 1)) / std.view(1, 3, 1, 1)  # transforms.Normalize
    x = x * (std / 0.5).view(1, 3, 1, 1) + ((mean - 0.5) / 0.5).view(1, 3, 1, 1)  # Inception3._transform_input
    x = torch.nn.functional.interpolate(x, size=(75, 75), mode="bilinear", align_corners=False)
    base = encoder.frozen_base().net
    assert isinstance(base, InceptionV3Base)
    with torch.no_grad():
        assert torch.allclose(base(images), base.net(x), atol=1e-4)


def test_missing_weights_say_where_to_put_the_file(tmp_path):
    with pytest.raises(BenchError) as empty:
        InceptionEncoder(spec(""), (24, 40), 0)
    message = str(empty.value)
    assert "\n" not in message
    for part in ("encoder.model.base.weights", "inception_v3 IMAGENET1K_V1 state_dict",
                 "mftcn-bench run --encoder inception --set encoder.model.base.weights="):
        assert part in message
    with pytest.raises(BenchError, match="weights file .*nothere.pth not found.*IMAGENET1K_V1"):
        InceptionEncoder(spec(tmp_path / "nothere.pth"), (24, 40), 0)


def test_a_wrong_file_is_one_line(tmp_path):
    state = dict(InceptionV3ToMixed5d().state_dict())
    del state["Mixed_5d.branch_pool.bn.running_mean"]
    torch.save(state, tmp_path / "partial.pth")
    with pytest.raises(BenchError, match="cannot be loaded \\(RuntimeError") as info:
        InceptionEncoder(spec(tmp_path / "partial.pth"), (24, 40), 0)
    assert "\n" not in str(info.value)


def test_spec_validation():
    with pytest.raises(SpecError, match="bad \\[model.base\\] table"):
        InceptionEncoder(spec(model={"base": {"name": "inception-v3", "bogus": 1}}), (24, 40), 0)
    with pytest.raises(SpecError, match="input_size must be >= 75"):
        BaseConfig(name="inception-v3", input_size=50)
    with pytest.raises(SpecError, match="embedding_dim 288"):
        InceptionEncoder(spec(embedding_dim=32), (24, 40), 0)
    with pytest.raises(SpecError, match="\\[train\\] table must be empty"):
        InceptionEncoder(spec(train={"steps": 3}), (24, 40), 0)


def test_registered_spec_needs_weights():
    entry = get("encoders", "inception")
    assert entry.spec.embedding_dim == 288 and entry.spec.model["base"]["input_size"] == 299
    with pytest.raises(BenchError, match="encoder.model.base.weights"):
        entry.load()(entry.spec, image_shape=(48, 96), seed=0)



def test_the_onnxruntime_engine_runs_inception_within_1e_4_of_eager(one_torch_thread, tmp_path):
    path = torchvision_file(tmp_path, perturbed_module())
    eager = InceptionEncoder(spec(path), image_shape=(24, 40), seed=0)
    fast = InceptionEncoder(spec(path, engine="onnxruntime"), image_shape=(24, 40), seed=0)
    frames = np.random.default_rng(0).integers(0, 255, (3, 24, 40, 3), dtype=np.uint8)
    expected, got = eager.embed(ClipBatch(frames[:, None])), fast.embed(ClipBatch(frames[:, None]))
    assert np.abs(got - expected).max() < 1e-4 * max(1.0, float(np.abs(expected).max()))
