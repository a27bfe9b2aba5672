import numpy as np
from sklearn.metrics import mean_squared_error

from mftcn_bench.data.dataset import ensure_dataset
from mftcn_bench.data.synthetic import synthetic_collector, synthetic_config
from mftcn_bench.encoders.base import EncoderInfo
from mftcn_bench.tasks.probe import TARGETS, CartpoleProbe, probe_features, state_targets, summarize


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
