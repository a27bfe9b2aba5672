"""Synthetic datasets for tests: frame pixel values encode (view, episode, t); nothing is rendered."""

import numpy as np


def synthetic_collector(config, index):
    """A collector that renders nothing: frame pixel values encode (view, episode, t)."""
    length, h, w = int(config["episode_length"]), int(config["height"]), int(config["width"])
    views = len(config["cameras"])
    t = np.arange(length)
    frames = np.zeros((views, length, h, w, 3), dtype=np.uint8)
    for v in range(views):
        frames[v] = ((v * 100 + index * 7 + t) % 256).astype(np.uint8)[:, None, None, None]
    rng = np.random.default_rng([int(config["seed"]), index])
    state = rng.normal(size=(length, 4))
    action = rng.uniform(-1, 1, size=(length, 1)).astype(np.float32)
    return {"frames": frames, "state": state, "action": action}


def synthetic_config(**changes):
    config = {"name": "synthetic", "cameras": ["a", "b"], "height": 8, "width": 12, "train_episodes": 3,
              "test_episodes": 1, "episode_length": 40, "seed": 0}
    config.update(changes)
    return config
