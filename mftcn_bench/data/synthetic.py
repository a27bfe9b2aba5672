"""Synthetic datasets for tests and `mftcn-bench check`: frame pixel values encode (view, episode, t);
nothing is rendered. With `pattern = "gradient"` in the config each frame also varies over its rows,
columns and channels, so a transposed or flipped image gives other embeddings."""

from collections.abc import Mapping
from typing import Any

import numpy as np


def synthetic_collector(config: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
    """A collector that renders nothing: frame pixel values encode (view, episode, t)."""
    length, h, w = int(config["episode_length"]), int(config["height"]), int(config["width"])
    views = len(config["cameras"])
    t = np.arange(length)
    frames = np.zeros((views, length, h, w, 3), dtype=np.uint8)
    texture = 0
    if config.get("pattern", "flat") == "gradient":
        rows, cols, chans = np.ogrid[:h, :w, :3]
        texture = (rows * 5 + cols * 3 + chans * 40)[None]
    for v in range(views):
        frames[v] = ((v * 100 + index * 7 + t[:, None, None, None] + texture) % 256).astype(np.uint8)
    rng = np.random.default_rng([int(config["seed"]), index])
    state = rng.normal(size=(length, 4))
    action = rng.uniform(-1, 1, size=(length, 1)).astype(np.float32)
    return {"frames": frames, "state": state, "action": action}


def synthetic_config(**changes: Any) -> dict[str, Any]:
    config = {"name": "synthetic", "cameras": ["a", "b"], "height": 8, "width": 12, "train_episodes": 3,
              "test_episodes": 1, "episode_length": 40, "seed": 0}
    config.update(changes)
    return config
