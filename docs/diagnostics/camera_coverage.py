"""Diagnostic: how often does each camera of a cartpole dataset show the cart and the pole?

Replays every frame's recorded state (x, theta) in the suite's cartpole model and projects the cart box's
eight corners, its centre and the pole's tip through each camera of the dataset at the dataset's image size
(MuJoCo's pinhole camera: vertical field of view `fovy`, horizontal from the aspect ratio). Prints, per
camera, the fraction of frames in which the cart is cut by the image's edge, its centre is outside the image,
and the pole's tip is outside it, with the distribution of |x|. Geometry only, nothing is rendered, so a
dataset of 180,000 frames takes seconds; tests/test_diagnostics.py checks it against MuJoCo's segmentation
render. Used to ask whether the fixed camera at 160x160 (a square image, so half of 96x48's horizontal
field) is why the swing-up rows do not gain from the resolution as the paper's do (docs/RESULTS.md).

    python docs/diagnostics/camera_coverage.py $MFTCN_BENCH_HOME/datasets/cartpole-agent-rate-<id>
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from itertools import product
from pathlib import Path

import numpy as np

from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.sim.rendering import ensure_gl


@dataclass(frozen=True)
class Coverage:
    """Per frame: the cart cut by the image's edge, its centre outside the image, the pole's tip outside."""

    cart_cut: np.ndarray
    cart_centre_out: np.ndarray
    tip_out: np.ndarray


def cartpole_physics():  # -> dm_control.mujoco.Physics, imported after `ensure_gl` picks the GL back end
    """The suite's cartpole physics (swing-up's model: the same cameras and geoms as the datasets')."""
    ensure_gl()
    from dm_control import suite

    return suite.load("cartpole", "swingup").physics


def _in_view(physics, camera: int, points: np.ndarray, aspect: float) -> np.ndarray:
    """Whether each world point [N, 3] projects inside the image of `camera` (MuJoCo looks along -z)."""
    position, rotation = physics.data.cam_xpos[camera], physics.data.cam_xmat[camera].reshape(3, 3)
    local = (points - position) @ rotation
    depth = -local[:, 2]
    half = np.tan(np.radians(physics.model.cam_fovy[camera]) / 2) * depth
    return (depth > 0) & (np.abs(local[:, 0]) <= half * aspect) & (np.abs(local[:, 1]) <= half)


def coverage(physics, camera: str, height: int, width: int, states: np.ndarray) -> Coverage:
    """What of the cart and pole `camera` shows at height x width for each state [T, >=2] (x, theta, ...)."""
    camera_id = physics.model.name2id(camera, "camera")
    cart, pole = physics.model.name2id("cart", "geom"), physics.model.name2id("pole_1", "geom")
    signs = np.array(list(product((-1, 1), repeat=3)), dtype=np.float64)
    cut, centre_out, tip_out = (np.zeros(len(states), dtype=bool) for _ in range(3))
    for t, (x, theta) in enumerate(states[:, :2]):
        physics.data.qpos[:] = (x, theta)
        physics.forward()
        centre = physics.data.geom_xpos[cart]
        corners = centre + (signs * physics.model.geom_size[cart]) @ physics.data.geom_xmat[cart].reshape(3, 3).T
        # the pole is a capsule along its local z (radius size[0], half-length size[1]); its tip is the end
        # away from the hinge on the cart
        reach = physics.data.geom_xmat[pole].reshape(3, 3)[:, 2] * physics.model.geom_size[pole][:2].sum()
        ends = physics.data.geom_xpos[pole] + np.stack([reach, -reach])
        tip = ends[np.argmax(np.linalg.norm(ends - centre, axis=1))]
        seen = _in_view(physics, camera_id, np.vstack([corners, centre, tip]), width / height)
        cut[t], centre_out[t], tip_out[t] = not seen[:8].all(), not seen[8], not seen[9]
    return Coverage(cut, centre_out, tip_out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="a collected cartpole dataset folder")
    parser.add_argument("--cameras", help="comma-separated cameras (default: the dataset's)")
    args = parser.parse_args()
    dataset = MultiViewDataset(args.dataset)
    height, width = dataset.image_shape
    # the states only: loading whole episodes would decompress every frame
    states = np.concatenate([np.load(dataset.root / chunk["file"])["state"] for chunk in dataset.manifest["chunks"]])
    distance = np.abs(states[:, 0])
    print(f"{dataset.dataset_id}: {len(states)} frames at {width}x{height}; |x| median {np.median(distance):.3f}, "
          f"90th percentile {np.quantile(distance, 0.9):.3f}, max {distance.max():.3f}")
    physics = cartpole_physics()
    for camera in args.cameras.split(",") if args.cameras else dataset.cameras:
        seen = coverage(physics, camera, height, width, states)
        print(f"{camera}: cart cut by the edge {seen.cart_cut.mean():.3f}, cart centre outside "
              f"{seen.cart_centre_out.mean():.3f}, pole tip outside {seen.tip_out.mean():.3f}")


if __name__ == "__main__":
    main()
