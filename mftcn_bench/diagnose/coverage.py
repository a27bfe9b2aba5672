"""Where the cart is in each camera's image: cartpole states projected through the suite's cameras.

A state's cart position and pole angle are set in the suite's cartpole model and the cart box's eight
corners, its centre and the pole's tip are projected through a camera at an image size (MuJoCo's pinhole
camera: vertical field of view `fovy`, horizontal from the aspect ratio). Per state: the cart cut by the
image's edge, its centre outside the image, the pole's tip outside it. Geometry only, nothing is rendered,
so a data set of 180,000 frames takes seconds (tests/test_diagnose.py checks it against MuJoCo's segmentation
render). `dataset_coverage` summarises a collected cartpole data set: the distribution of |x| and, per camera,
how often each of the three happens. It answered whether the fixed camera's square 160x160 image (half of
96x48's horizontal field) is why the swing-up rows do not gain from the resolution (docs/FINDINGS.md).
"""

from __future__ import annotations

import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import product
from typing import Any

import numpy as np

from mftcn_bench.core.errors import DataError, SpecError, did_you_mean
from mftcn_bench.data.dataset import MultiViewDataset
from mftcn_bench.sim.rendering import ensure_gl


@dataclass(frozen=True)
class Coverage:
    """Per state: the cart cut by the image's edge, its centre outside the image, the pole's tip outside."""

    cart_cut: np.ndarray
    cart_centre_out: np.ndarray
    tip_out: np.ndarray


@dataclass(frozen=True)
class CoverageFractions:
    """One camera's `Coverage` over many states, as the fraction of states in which each happens."""

    camera: str
    cart_cut: float
    cart_centre_out: float
    tip_out: float

    @classmethod
    def of(cls, camera: str, seen: Coverage) -> CoverageFractions:
        return cls(camera, float(seen.cart_cut.mean()), float(seen.cart_centre_out.mean()), float(seen.tip_out.mean()))


@dataclass(frozen=True)
class CartRange:
    """The distribution of the cart's distance from the rail's centre, |x| in metres."""

    median: float
    p90: float
    max: float

    @classmethod
    def of(cls, states: np.ndarray) -> CartRange:
        distance = np.abs(states[:, 0])
        return cls(float(np.median(distance)), float(np.quantile(distance, 0.9)), float(distance.max()))


@dataclass(frozen=True)
class DatasetCoverage:
    """`dataset_coverage`'s answer: the data set, its frame count and size, |x| and each camera's fractions."""

    dataset_id: str
    frames: int
    height: int
    width: int
    cart: CartRange
    cameras: tuple[CoverageFractions, ...]


def cartpole_physics() -> Any:  # a dm_control.mujoco.Physics; dm_control is imported after `ensure_gl`
    """The suite's cartpole physics (swing-up's model: the same cameras and geoms as the data sets')."""
    ensure_gl()  # dm_control picks its GL back end when it is imported
    from dm_control import suite

    return suite.load("cartpole", "swingup").physics


def _in_view(physics: Any, camera: int, points: np.ndarray, aspect: float) -> np.ndarray:
    """Whether each world point [N, 3] projects inside the image of `camera` (MuJoCo looks along -z)."""
    position, rotation = physics.data.cam_xpos[camera], physics.data.cam_xmat[camera].reshape(3, 3)
    local = (points - position) @ rotation
    depth = -local[:, 2]
    half = np.tan(np.radians(physics.model.cam_fovy[camera]) / 2) * depth
    return (depth > 0) & (np.abs(local[:, 0]) <= half * aspect) & (np.abs(local[:, 1]) <= half)


def coverage(physics: Any, camera: str, height: int, width: int, states: np.ndarray) -> Coverage:
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


def pick_cameras(available: Sequence[str], asked: Sequence[str] | None) -> list[str]:
    """`asked` (all of `available` when None), each checked against `available`; an unknown one is one line."""
    if asked is None:
        return list(available)
    if not asked:
        raise SpecError(f"--cameras names no camera; valid: {', '.join(available)}")
    for camera in asked:
        if camera not in available:
            raise SpecError(did_you_mean("camera", camera, list(available)))
    return list(asked)


def dataset_states(dataset: MultiViewDataset) -> np.ndarray:
    """Every frame's recorded state [N, S], in the manifest's order, read without the frames."""
    parts = []
    for chunk in dataset.manifest["chunks"]:
        path = dataset.root / chunk["file"]
        # only the state's member of each chunk: loading whole episodes would decompress every frame
        try:
            with np.load(path, allow_pickle=False) as npz:
                parts.append(npz["state"])
        except (FileNotFoundError, KeyError, zipfile.BadZipFile, ValueError, OSError) as exc:
            raise DataError(f"dataset chunk {path} cannot be read ({type(exc).__name__}); delete the dataset "
                            f"folder {dataset.root} to collect it again") from None
    return np.concatenate(parts)


def dataset_coverage(dataset: MultiViewDataset, cameras: Sequence[str] | None = None) -> DatasetCoverage:
    """|x| over every frame of a cartpole data set and, per camera (default the data set's), the fractions of
    frames whose cart is cut, whose cart centre is outside the image and whose pole tip is outside it."""
    domain = dataset.config.get("domain")
    if domain != "cartpole":
        raise DataError(f"{dataset.root} is a {domain or 'non-simulator'} data set; diagnose coverage reads "
                        f"cartpole data sets (cartpole-random, cartpole-agent-rate)")
    picked = pick_cameras(dataset.cameras, cameras)
    height, width = dataset.image_shape
    states = dataset_states(dataset)
    physics = cartpole_physics()
    fractions = tuple(CoverageFractions.of(camera, coverage(physics, camera, height, width, states))
                      for camera in picked)
    return DatasetCoverage(dataset.dataset_id, len(states), height, width, CartRange.of(states), fractions)
