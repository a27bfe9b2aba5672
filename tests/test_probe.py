import numpy as np
from sklearn.metrics import mean_squared_error

from mftcn_bench.data.cartpole import TARGETS, state_targets
from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config
from mftcn_bench.encoders.base import EncoderInfo
from mftcn_bench.tasks.probe import CartpoleProbe, probe_features, summarize


def test_targets_and_features():
    state = np.array([[0.5, np.pi / 2, 1.0, -2.0], [0.0, 0.0, 0.0, 0.0]])
    assert np.allclose(state_targets(state), [[0.5, 1.0, 0.0, 1.0, -2.0], [0.0, 0.0, 1.0, 0.0, 0.0]])
    e = np.array([[1.0, 2.0], [4.0, 3.0], [5.0, 5.0]])
    assert probe_features(e).tolist() == [[1, 2, 0, 0], [4, 3, 3, 1], [5, 5, 1, 2]]


def test_summary_means():
    out = summarize(dict(zip(TARGETS, [1.0, 2.0, 3.0, 10.0, 20.0], strict=True)))
    assert out["position"] == 2.0 and out["motion"] == 15.0 and out["average"] == 7.2


class StateEncoder:
    """Embeds the true state of the clip's last frame (a perfect encoder of positions)."""

    info = EncoderInfo("state", 1, 1, (8, 12), 4, 0)
    privileged_inputs = ("state",)
    needs_fit = False

    def embed(self, clips):
        return clips.state[:, -1].astype(np.float32)


class NoiseEncoder(StateEncoder):
    def embed(self, clips):
        return np.random.default_rng(len(clips.state)).normal(size=(len(clips.state), 4)).astype(np.float32)


def probe_config():
    dataset = synthetic_config(train_episodes=6, episode_length=200, cameras=["fixed", "lookatcart"])
    return {"name": "cartpole-probe", "dataset": dataset,
            "probe": {"camera": "fixed", "hidden": [32, 32, 32], "lr": 0.003, "epochs": 200, "batch_size": 64,
                      "tol": 1e-6, "early_stopping": True, "validation_fraction": 0.1, "patience": 10}}


def test_probe_reads_state_from_a_perfect_encoder_and_not_from_noise(tmp_path):
    config = probe_config()
    dataset = ensure_dataset(tmp_path, config["dataset"], synthetic_collector, show_progress=False)
    probe = CartpoleProbe(config, seed=0)
    good = probe.evaluate(StateEncoder(), dataset).metrics
    bad = probe.evaluate(NoiseEncoder(), dataset).metrics
    assert good["average"] < 0.2 * bad["average"]
    # metrics are sklearn's MSE against the test split's targets
    y = np.concatenate([state_targets(e.state) for e in dataset.iter_episodes("test")])
    assert np.isclose(bad["var_x_cart"], y[:, 0].var())
    baseline = mean_squared_error(y[:, 0], np.full(len(y), y[:, 0].mean()))
    assert bad["mse_x_cart"] > 0.8 * baseline and good["mse_x_cart"] < 0.2 * baseline


def scaled_collector(config, index):
    """The cart position (on a 1 cm scale, next to a theta_dot on a 10 rad/s scale) drawn into the fixed
    camera's pixels only; the other camera sees noise."""
    out = synthetic_collector(config, index)
    t = np.arange(len(out["state"]))
    rng = np.random.default_rng([11, index])
    x = 0.01 * np.sin(t / 9.0 + index)
    state = np.stack([x, rng.uniform(-np.pi, np.pi, len(t)), rng.normal(size=len(t)),
                      10 * rng.normal(size=len(t))], axis=1)
    frames = out["frames"]
    frames[0] = np.round((x / 0.01 + 1) * 127).astype(np.uint8)[:, None, None, None]
    frames[1] = rng.integers(0, 255, frames[1].shape, dtype=np.uint8)
    return {**out, "state": state}


class PixelEncoder(StateEncoder):
    """Reads only pixels: the mean brightness of the clip's last frame."""

    info = EncoderInfo("pixels", 1, 1, (8, 12), 1, 0)

    def embed(self, clips):
        return (clips.frames[:, -1].mean(axis=(1, 2, 3)) / 127.0 - 1.0)[:, None].astype(np.float32)


def test_the_probe_reads_its_camera_and_weighs_a_small_scale_target(tmp_path):
    """Standardised targets: the 1 cm cart position is learnt beside a theta_dot 1000x its scale; and the
    probe embeds its own camera's frames (the other camera carries nothing)."""
    config = probe_config()
    dataset = ensure_dataset(tmp_path, config["dataset"], scaled_collector, show_progress=False)
    fixed = CartpoleProbe(config, seed=0).evaluate(PixelEncoder(), dataset).metrics
    assert fixed["r2_x_cart"] > 0.9 and fixed["var_x_cart"] < 1e-4
    assert fixed["r2_theta_dot"] < 0.1, "nothing in the pixels says theta_dot"
    other = {**config, "probe": {**config["probe"], "camera": "lookatcart"}}
    wrong = CartpoleProbe(other, seed=0).evaluate(PixelEncoder(), dataset).metrics
    assert wrong["r2_x_cart"] < 0.2
