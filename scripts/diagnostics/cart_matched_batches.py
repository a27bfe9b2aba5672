"""Diagnostic: does mfTCN's n-pairs objective find the pole when the cart cannot tell time steps apart?

Trains mfTCN1's network (`encoders/mftcn1.toml`'s [model], [train] lr, weight decay, reg_lambda and alpha)
with the multi-view n-pairs loss on batches of K time steps, then probes the embedding of the `fixed`
camera for x_cart, sin theta and cos theta (an MLP of two hidden layers of 256 from scikit-learn on 6,000
train frames, MSE on the test split) every `--probe-every` steps. Batches are either

- `random`: K time steps drawn at random from all train frames (at least alpha frames apart within an
  episode), or
- `cart-matched`: K time steps whose true cart position lies within `--tolerance` m of a random frame's
  (the same gap rule). The cart then carries no information about which time step is which, so only the
  pole (and whatever else differs) can lower the loss. This uses the true state to build batches, so it is a
  diagnostic, not an encoder.

Used to tell "the objective gains nothing from the pole" apart from "the objective would gain from the pole
but does not find it from a random start" (see the README's cartpole-probe results).

    python scripts/diagnostics/cart_matched_batches.py $MFTCN_BENCH_HOME/datasets/cartpole-random-<id> \
        [--batches cart-matched|random] [--steps 1500]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from sklearn.neural_network import MLPRegressor

from mftcn_bench.core import registry
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.encoders.losses import multiview_npairs_loss
from mftcn_bench.encoders.mftcn import MfTCNModelConfig, MfTCNNet


def from_scratch(model: dict) -> MfTCNModelConfig:
    """mftcn1's [model] with the from-scratch small-cnn base: the design this diagnostic was written for."""
    return MfTCNModelConfig.from_table("mftcn1", {**model, "base": {"name": "small-cnn"}})

def load_split(dataset: MultiViewDataset, split: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All frames of a split: [views, N, H, W, 3], states [N, 4], episode of each frame, time of each frame."""
    episodes = list(dataset.iter_episodes(split))
    frames = np.concatenate([e.frames for e in episodes], axis=1)
    states = np.concatenate([e.state for e in episodes])
    episode = np.concatenate([np.full(len(e.state), k) for k, e in enumerate(episodes)])
    time_step = np.concatenate([np.arange(len(e.state)) for e in episodes])
    return frames, states, episode, time_step


def pick_spread(candidates: np.ndarray, episode: np.ndarray, time_step: np.ndarray, count: int,
                gap: int) -> np.ndarray:
    """Up to `count` of `candidates` (in their order) no two of which are closer than `gap` in one episode."""
    picked: list[int] = []
    for c in candidates:
        if all(episode[c] != episode[p] or abs(int(time_step[c]) - int(time_step[p])) >= gap for p in picked):
            picked.append(int(c))
            if len(picked) == count:
                break
    return np.array(picked)


def targets(states: np.ndarray) -> np.ndarray:
    return np.stack([states[:, 0], np.sin(states[:, 1]), np.cos(states[:, 1])], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="a collected cartpole-random dataset folder")
    parser.add_argument("--batches", choices=["cart-matched", "random"], default="cart-matched")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--timesteps", type=int, default=16, help="K, time steps per batch")
    parser.add_argument("--tolerance", type=float, default=0.05, help="cart-matched: |x - x0| in m")
    parser.add_argument("--probe-every", type=int, default=500)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)

    spec = registry.get("encoders", "mftcn1").spec
    train = dict(spec.train)
    net = MfTCNNet(from_scratch(spec.model), frames=1,
                   embedding_dim=spec.embedding_dim)
    opt = torch.optim.Adam(net.parameters(), lr=train["lr"], weight_decay=train["weight_decay"])
    dataset = MultiViewDataset(args.dataset)
    frames, states, episode, time_step = load_split(dataset, "train")
    test_frames, test_states, _, _ = load_split(dataset, "test")

    def clips(view_frames: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(view_frames).permute(0, 3, 1, 2)[:, None]

    def embed(view_frames: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return torch.cat([net(clips(view_frames[i:i + 512])) for i in range(0, len(view_frames), 512)]).numpy()

    def probe() -> np.ndarray:
        rows = rng.choice(len(states), size=min(6000, len(states)), replace=False)
        x, x_test = embed(frames[0, rows]), embed(test_frames[0])
        mean, std = x.mean(0), x.std(0) + 1e-6
        mlp = MLPRegressor(hidden_layer_sizes=(256, 256), max_iter=200, early_stopping=True, random_state=0)
        mlp.fit((x - mean) / std, targets(states[rows]))
        return ((mlp.predict((x_test - mean) / std) - targets(test_states)) ** 2).mean(0)

    variance = targets(test_states).var(0)
    print(f"test variance: x_cart {variance[0]:.3f} sin {variance[1]:.3f} cos {variance[2]:.3f}; "
          f"batches {args.batches}, K {args.timesteps}, chance loss log K = {np.log(args.timesteps):.3f}")
    began, losses = time.monotonic(), []
    for step in range(args.steps + 1):
        if step % args.probe_every == 0 or step == args.steps:
            mse = probe()
            recent = f"{np.mean(losses[-100:]):.3f}" if losses else "-"
            print(f"step {step}: n-pairs loss (mean of last 100) {recent}; probe MSE x_cart {mse[0]:.3f} "
                  f"sin {mse[1]:.3f} cos {mse[2]:.3f}; {time.monotonic() - began:.0f} s", flush=True)
        if step == args.steps:
            break
        if args.batches == "cart-matched":
            x0 = states[rng.integers(len(states)), 0]
            candidates = rng.permutation(np.flatnonzero(np.abs(states[:, 0] - x0) < args.tolerance))
        else:
            candidates = rng.permutation(len(states))[: 64 * args.timesteps]
        rows = pick_spread(candidates, episode, time_step, args.timesteps, train["alpha"])
        if len(rows) < 2:
            continue
        embeddings = net(torch.cat([clips(frames[0, rows]), clips(frames[1, rows])]))
        loss = multiview_npairs_loss(embeddings.reshape(2, len(rows), -1), train["reg_lambda"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())


if __name__ == "__main__":
    main()
