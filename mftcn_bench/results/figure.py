"""Matplotlib on its Agg backend for every PNG the harness draws: saving a figure, and the one-run
learning curve that the runner writes beside each run.

Kept apart from `plots` because a run's id covers the runner's import closure (`core.identity`): the
runner imports this module only, so a change to the paper tables or the report plots re-keys no run.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - the backend is chosen first
import numpy as np  # noqa: E402

__all__ = ["plot_run_curve", "plt", "save_figure"]


def save_figure(fig, path: Path) -> Path:
    """Write `fig` to `path` (parents made) and close it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_run_curve(curve: dict[str, list[float]], path: Path, title: str) -> Path:
    """One run's training return against frames and against wall time, side by side (`curve.png` in the
    run's folder)."""
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    axes[0].plot(np.asarray(curve["frames"]) / 1e6, curve["return"])
    axes[0].set(xlabel="frames (millions)", ylabel="training return")
    axes[1].plot(np.asarray(curve["wall_s"]) / 60, curve["return"])
    axes[1].set(xlabel="wall time (min)")
    fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)
