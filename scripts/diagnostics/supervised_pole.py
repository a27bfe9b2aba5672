"""Diagnostic: can the mfTCN network represent the cartpole pole at all?

Trains mfTCN1's network (base CNN with coordinate channels, 3D convolution, spatial average, fully connected
layer; `encoders/mftcn1.toml`'s [model]) to regress (sin theta, cos theta) directly from single frames of
one camera of a collected cartpole dataset, and prints the test MSE as it goes. Used to tell "the network
cannot see the pole" apart from "the time-contrastive objective does not make it encode the pole" (see the
README's cartpole-probe results).

    python scripts/diagnostics/supervised_pole.py $MFTCN_BENCH_HOME/datasets/cartpole-random-<id> [--view 0]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from mftcn_bench.core import registry
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.mftcn import MfTCNModelConfig, MfTCNNet


def from_scratch(model: dict) -> MfTCNModelConfig:
    """mftcn1's [model] with the from-scratch small-cnn base: the design this diagnostic was written for."""
    return MfTCNModelConfig.from_table("mftcn1", {**model, "base": {"name": "small-cnn"}})

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="a collected cartpole-random dataset folder")
    parser.add_argument("--view", type=int, default=0, help="camera index (0: fixed, 1: lookatcart)")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--batch", type=int, default=64)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)

    dataset = MultiViewDataset(args.dataset)
    splits = {}
    for split in ("train", "test"):
        episodes = list(dataset.iter_episodes(split))
        frames = np.concatenate([e.frames[args.view] for e in episodes])
        theta = np.concatenate([e.state[:, 1] for e in episodes])
        splits[split] = (frames, np.stack([np.sin(theta), np.cos(theta)], 1).astype(np.float32))
    spec = registry.get("encoders", "mftcn1").spec
    net = MfTCNNet(from_scratch(spec.model), frames=1, embedding_dim=2)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)

    def tensors(split: str, index: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        frames, targets = splits[split]
        return torch.from_numpy(frames[index]).permute(0, 3, 1, 2)[:, None], torch.from_numpy(targets[index])

    test_index = np.arange(len(splits["test"][0]))
    began = time.monotonic()
    for step in range(args.steps + 1):
        if step % 250 == 0 or step == args.steps:
            with torch.no_grad():
                x, y = tensors("test", test_index)
                mse = ((net(x) - y) ** 2).mean(0).numpy()
            print(f"step {step}: test MSE sin {mse[0]:.4f} cos {mse[1]:.4f} (variance "
                  f"{y[:, 0].var():.4f} {y[:, 1].var():.4f}); {time.monotonic() - began:.0f} s", flush=True)
        if step == args.steps:
            break
        x, y = tensors("train", rng.integers(0, len(splits["train"][0]), args.batch))
        loss = ((net(x) - y) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()


if __name__ == "__main__":
    main()
