"""How far a PPO run got: the frames and the last training return in the checkpoint a running or killed
run left in its folder (written by `rl.ppo.train_ppo`), for `sweep status`.

A module of its own, outside `rl.ppo`'s import closure: editing `rl.ppo` re-keys every control run
(`core.identity`), and the status must not need torchrl to read two numbers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

CHECKPOINT = "ppo_checkpoint.pt"  # the name `rl.ppo.train_ppo` saves under, in the run's folder


@dataclass(frozen=True)
class CheckpointProgress:
    frames: int                  # physics frames trained, as `task.ppo.frames` counts them
    last_return: float | None    # the mean training return of the last batch before the checkpoint


def checkpoint_progress(run_dir: Path) -> CheckpointProgress | None:
    """The progress saved in `run_dir`'s PPO checkpoint; None when there is none or it cannot be read (a
    run that is writing it replaces it atomically, so that means a damaged file, which the run reports)."""
    path = run_dir / CHECKPOINT
    if not path.is_file():
        return None
    import torch

    try:
        state = torch.load(path, weights_only=True, map_location="cpu")["state"]
        returns = state["curve_return"]
        return CheckpointProgress(int(state["frames"]), float(returns[-1]) if returns else None)
    except Exception:  # noqa: BLE001 - a status line, not the run: the run itself says what is wrong
        return None
