"""The MJCF scene of simulated pouring, built in code from the spec's `[dataset.scene]` table.

World: a table (the plane z = 0), a recipient cup fixed to the table, a pouring container on a free joint,
a mocap "hand" (visual only: it never collides; a weld equality, off at first, holds the container while
grasped) and the liquid as beads. Beads are frictionless spheres (condim 1, and a higher priority so the
contact takes their condim) on three slide joints each instead of a free joint, with mixed sizes and some
joint damping: far cheaper to simulate, and they pour as a steady stream. The container is filled through an invisible
tube on its rim (geoms of class "tube", switched off after the beads settle): beads dropped from random
places pack randomly, and a random packing flows where a lattice jams. Sphere tessellation is lowered
(`sphere_slices`, `sphere_stacks`), which halves rendering time at these image sizes.

Frames: the container's body origin is the centre of its base, its z axis the axis of the cylinder; the
cup's likewise. Bead bodies sit at the world origin so a bead's three joint positions are its world
position. Per-episode randomisation (positions, colours, lights, cameras) changes the compiled model's
arrays; the XML depends on the scene table only.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

CAMERAS = ("fixed", "orbit")


def bead_radii(scene: Mapping[str, Any]) -> np.ndarray:
    """Radii of the beads: evenly spread over the size range, in a fixed shuffled order."""
    low, high = scene["bead_size_spread"]
    radii = float(scene["bead_radius"]) * np.linspace(low, high, int(scene["beads"]))
    return radii[np.random.default_rng(0).permutation(len(radii))]


def _walls(name: str, radius: float, height: float, thickness: float, segments: int, material: str | None,
           bottom: float = 0.0, base: bool = True) -> str:
    """An open-topped polygonal cylinder: a disc base and `segments` box walls (inner radius `radius`) from
    z = `bottom` up; without a material the walls are invisible (class "tube")."""
    half_width = radius * np.tan(np.pi / segments) + thickness  # overlapping corners: no gaps
    look = f'class="wall" material="{material}"' if material else 'class="tube"'
    parts = []
    if base:
        parts.append(f'<geom name="{name}_base" {look} type="cylinder" size="{radius + thickness:.5f} '
                     f'{thickness / 2:.5f}" pos="0 0 {thickness / 2:.5f}"/>')
    for i in range(segments):
        angle = 2 * np.pi * i / segments
        r = radius + thickness / 2
        parts.append(
            f'<geom name="{name}_wall{i}" {look} type="box" size="{thickness / 2:.5f} {half_width:.5f} '
            f'{height / 2:.5f}" pos="{r * np.cos(angle):.5f} {r * np.sin(angle):.5f} {bottom + height / 2:.5f}" '
            f'euler="0 0 {np.degrees(angle):.4f}"/>')  # MJCF angles are degrees
    return "\n".join(parts)


def scene_xml(scene: Mapping[str, Any]) -> str:
    """The MJCF text of the pouring scene for a `[dataset.scene]` table."""
    t = float(scene["wall_thickness"])
    segments = int(scene["wall_segments"])
    beads = []
    for i, radius in enumerate(bead_radii(scene)):
        beads.append(
            f'<body name="bead{i}"><joint name="bead{i}_x" type="slide" axis="1 0 0"/>'
            f'<joint name="bead{i}_y" type="slide" axis="0 1 0"/><joint name="bead{i}_z" type="slide" '
            f'axis="0 0 1"/><geom class="bead" size="{radius:.5f}"/></body>')
    hand_width = float(scene["container_radius"]) + t
    return f"""<mujoco model="pouring">
  <option timestep="{float(scene['timestep'])}" iterations="{int(scene['solver_iterations'])}"
          ls_iterations="{int(scene['solver_iterations'])}"/>
  <visual>
    <quality numslices="{int(scene['sphere_slices'])}" numstacks="{int(scene['sphere_stacks'])}"/>
    <headlight ambient="0.3 0.3 0.3" diffuse="0.3 0.3 0.3"/>
  </visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.55 0.65 0.8" rgb2="0.1 0.1 0.15" width="64"
             height="64"/>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.8 0.8 0.8" rgb2="0.6 0.6 0.6" width="64"
             height="64"/>
    <material name="table" texture="grid" texrepeat="8 8"/>
    <material name="container"/>
    <material name="cup"/>
    <material name="liquid"/>
    <material name="hand"/>
  </asset>
  <default>
    <default class="wall">
      <geom condim="3" friction="0.8 0.005 0.0001" solref="0.005 1"/>
    </default>
    <default class="tube">
      <geom condim="1" rgba="0 0 0 0" group="3"/>
    </default>
    <default class="bead">
      <geom type="sphere" condim="1" priority="1" material="liquid" density="{float(scene['bead_density'])}"
            solref="0.005 1"/>
      <joint damping="{float(scene['bead_damping'])}"/>
    </default>
    <default class="hand">
      <geom contype="0" conaffinity="0" material="hand" density="0"/>
    </default>
  </default>
  <worldbody>
    <light name="key" pos="0.3 -0.4 1.2" dir="-0.25 0.3 -1" directional="false" castshadow="true"
           diffuse="0.7 0.7 0.7"/>
    <geom name="table" type="plane" size="1 1 0.05" material="table" condim="3"/>
    <body name="lookat" pos="0 0 0.08"><inertial pos="0 0 0" mass="0.001" diaginertia="1e-6 1e-6 1e-6"/></body>
    <camera name="fixed" mode="targetbody" target="lookat" pos="0 -0.7 0.4"/>
    <camera name="orbit" mode="targetbody" target="lookat" pos="0.7 0 0.4"/>
    <body name="cup" pos="0.15 0 0">
      {_walls("cup", float(scene["cup_radius"]), float(scene["cup_height"]), t, segments, "cup")}
    </body>
    <body name="container" pos="-0.15 0 0">
      <freejoint name="container"/>
      {_walls("container", float(scene["container_radius"]), float(scene["container_height"]), t, segments,
              "container")}
      {_walls("tube", float(scene["container_radius"]), float(scene["fill_tube_height"]), t, segments, None,
              bottom=float(scene["container_height"]), base=False)}
    </body>
    <body name="hand" mocap="true" pos="-0.3 0.3 0.3">
      <geom class="hand" type="box" size="0.022 {hand_width + 0.008:.4f} 0.012" pos="-0.03 0 0"/>
      <geom class="hand" type="box" size="0.03 0.007 0.009" pos="0.012 {hand_width + 0.006:.4f} 0"/>
      <geom class="hand" type="box" size="0.03 0.007 0.009" pos="0.012 {-hand_width - 0.006:.4f} 0"/>
      <geom class="hand" type="capsule" size="0.018" fromto="-0.05 0 0 -0.16 0 0.06"/>
    </body>
    {"".join(beads)}
  </worldbody>
  <equality>
    <weld name="grasp" body1="hand" body2="container" active="false" solref="0.01 1"/>
  </equality>
</mujoco>
"""
