"""Simulated multi-view pouring: a scripted MuJoCo episode per seed, two synchronized views, exact labels.

Each episode (a pure function of the dataset config and the episode index) randomises the layout, colours,
lighting and camera paths, fills the container with beads, lets them settle, then runs the script: reach,
grasp (the weld switched on with the current relative pose, so nothing jumps), lift, carry to the
recipient, tilt and pour closed-loop (tilt fast until beads leave, then slowly, pausing while many are in
the air; once empty, on to a final tilt held a while), untilt, carry back, put down, release, recede. Hand
motions follow minimum-jerk profiles sampled at every physics step. Views: `fixed` (a random viewpoint
per episode) and `orbit` (circles the scene slowly). Every number lives in the spec's `[dataset.*]`
tables; the labels (see `pouring_labels`) come from the recorded state.
"""

from __future__ import annotations

import colorsys
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mftcn_bench.core.errors import DataError
from mftcn_bench.data.pouring_labels import STATE_COLUMNS, labels_from_state
from mftcn_bench.data.pouring_scene import CAMERAS, bead_radii, scene_xml
from mftcn_bench.sim.rendering import MultiViewRenderer, RenderSettings, ensure_gl

Z = np.array([0.0, 0.0, 1.0])


def min_jerk(s: float) -> float:
    """Minimum-jerk progress 0 -> 1 for phase fraction s in [0, 1]."""
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def axis_angle_quat(axis: np.ndarray, degrees: float) -> np.ndarray:
    half = np.radians(degrees) / 2.0
    return np.concatenate([[np.cos(half)], np.sin(half) * np.asarray(axis, dtype=np.float64)])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    import mujoco

    out = np.empty(4)
    mujoco.mju_mulQuat(out, a, b)
    return out


def quat_inv(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]]) / float(q @ q)


def quat_mat(q: np.ndarray) -> np.ndarray:
    import mujoco

    out = np.empty(9)
    mujoco.mju_quat2Mat(out, q)
    return out.reshape(3, 3)


@dataclass
class Pose:
    """A position and a unit quaternion (w, x, y, z)."""

    pos: np.ndarray
    quat: np.ndarray


def _uniform(rng: np.random.Generator, bounds: list[float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


class PouringEpisode:
    """One scripted episode: build and randomise the scene, then run the script frame by frame."""

    def __init__(self, config: Mapping[str, Any], index: int) -> None:
        ensure_gl()
        from dm_control.mujoco import Physics

        self.config = config
        self.rng = np.random.default_rng([int(config["seed"]), index])
        self.scene, self.layout = config["scene"], config["layout"]
        unknown = [c for c in config["cameras"] if c not in CAMERAS]
        if unknown:
            raise DataError(f"camera {unknown[0]!r} does not exist in pouring-sim; available: {', '.join(CAMERAS)}")
        self.physics = Physics.from_xml_string(scene_xml(self.scene))
        self.model, self.data = self.physics.model.ptr, self.physics.data.ptr
        timestep = float(self.scene["timestep"])
        self.substeps = max(1, round(1.0 / (float(config["fps"]) * timestep)))
        self.frame_seconds = self.substeps * timestep
        self.radius_in = float(self.scene["container_radius"])
        self.radius_out = self.radius_in + float(self.scene["wall_thickness"])
        self.height = float(self.scene["container_height"])
        self.beads = int(self.scene["beads"])
        self._ids()
        self._randomise()
        self.renderer = MultiViewRenderer(self.physics, config["cameras"], int(config["height"]),
                                          int(config["width"]),
                                          RenderSettings.from_table(f"dataset {config['name']!r}", config["render"]))

    # --- scene set-up -------------------------------------------------------------------------------------
    def _ids(self) -> None:
        import mujoco

        m = self.model

        def ident(kind, name):
            return mujoco.mj_name2id(m, kind, name)

        self.container_body = ident(mujoco.mjtObj.mjOBJ_BODY, "container")
        self.cup_body = ident(mujoco.mjtObj.mjOBJ_BODY, "cup")
        self.lookat_body = ident(mujoco.mjtObj.mjOBJ_BODY, "lookat")
        self.hand_mocap = int(m.body_mocapid[ident(mujoco.mjtObj.mjOBJ_BODY, "hand")])
        self.cams = {name: ident(mujoco.mjtObj.mjOBJ_CAMERA, name) for name in CAMERAS}
        self.materials = {name: ident(mujoco.mjtObj.mjOBJ_MATERIAL, name)
                          for name in ("table", "container", "cup", "liquid", "hand")}
        first_bead = ident(mujoco.mjtObj.mjOBJ_JOINT, "bead0_x")
        self.bead_qpos = int(m.jnt_qposadr[first_bead])
        self.bead_dof = int(m.jnt_dofadr[first_bead])
        self.bead_bodies = np.array([ident(mujoco.mjtObj.mjOBJ_BODY, f"bead{i}") for i in range(self.beads)])

    def _randomise(self) -> None:
        import mujoco

        rng, lay, m, d = self.rng, self.layout, self.model, self.data
        # layout: container and recipient on the table; the hand comes from one side of the container
        self.start = np.array([_uniform(rng, lay["container_x"]), _uniform(rng, lay["container_y"]), 0.0])
        self.cup = np.array([_uniform(rng, lay["cup_x"]), _uniform(rng, lay["cup_y"]), 0.0])
        m.body_pos[self.cup_body] = self.cup
        side = np.radians(_uniform(rng, lay["hand_side_degrees"])) * rng.choice([-1.0, 1.0])
        self.grip_dir = np.array([np.cos(side), np.sin(side), 0.0])  # from the container towards the hand
        tilt_dir = np.cross(Z, self.grip_dir)
        toward_cup = self.cup - self.start
        self.tilt_dir = tilt_dir if tilt_dir @ toward_cup >= 0 else -tilt_dir  # horizontal, towards the cup
        yaw = float(rng.uniform(-np.pi, np.pi))
        d.qpos[0:3] = self.start
        d.qpos[3:7] = axis_angle_quat(Z, np.degrees(yaw))
        self.hand_start = Pose(self.start + self.grip_dir * _uniform(rng, lay["hand_start_distance"])
                               + Z * _uniform(rng, lay["hand_start_height"]), self._hand_yaw_quat())
        self._set_hand(self.hand_start)
        self._fill_beads()
        # colours and light
        colours = self.config["colours"]
        for name in ("table", "container", "cup", "liquid", "hand"):
            h, s, v = (_uniform(rng, bounds) for bounds in colours[name])
            m.mat_rgba[self.materials[name], :3] = colorsys.hsv_to_rgb(h % 1.0, s, v)
        light = self.config["lighting"]
        angle = float(rng.uniform(0, 2 * np.pi))
        distance = _uniform(rng, light["distance"])
        m.light_pos[0] = [distance * np.cos(angle), distance * np.sin(angle), _uniform(rng, light["height"])]
        direction = np.array([0.0, 0.0, 0.05]) - m.light_pos[0]
        m.light_dir[0] = direction / np.linalg.norm(direction)
        m.light_diffuse[0] = _uniform(rng, light["diffuse"])
        m.vis.headlight.ambient[:] = _uniform(rng, light["ambient"])
        # cameras: a look-at point between container and recipient, a fixed view and an orbiting one
        cam = self.config["camera"]
        lookat = (self.start + self.cup) / 2 + np.array([*rng.normal(0, cam["lookat_jitter"], 2), cam["lookat_height"]])
        m.body_pos[self.lookat_body] = lookat
        self.lookat = lookat
        self.fixed_view = (_uniform(rng, cam["fixed_azimuth"]), _uniform(rng, cam["elevation"]),
                           _uniform(rng, cam["distance"]))
        self.orbit_start = (float(rng.uniform(-180, 180)), _uniform(rng, cam["elevation"]),
                            _uniform(rng, cam["distance"]))
        self.orbit_rate = _uniform(rng, cam["orbit_rate"]) * rng.choice([-1.0, 1.0])
        self.orbit_swing = (float(cam["orbit_elevation_swing"]), float(rng.uniform(0, 2 * np.pi)))
        mujoco.mj_forward(m, d)

    def _hand_yaw_quat(self) -> np.ndarray:
        towards = -self.grip_dir
        return axis_angle_quat(Z, np.degrees(np.arctan2(towards[1], towards[0])))

    def _fill_beads(self) -> None:
        """Beads at random places (no overlaps) in the column of the container and its fill tube; they fall
        and settle before the first frame."""
        radii = bead_radii(self.scene)
        floor = float(self.scene["wall_thickness"])
        top = self.height + float(self.scene["fill_tube_height"])
        placed = np.zeros((self.beads, 3))
        for k, radius in enumerate(radii):
            for _ in range(300):
                r = (self.radius_in - radius - 0.0005) * np.sqrt(self.rng.uniform())
                a = self.rng.uniform(0, 2 * np.pi)
                p = np.array([r * np.cos(a), r * np.sin(a), self.rng.uniform(floor + radius, top - radius)])
                if np.all(np.linalg.norm(placed[:k] - p, axis=1) > radii[:k] + radius + 0.0005):
                    break
            else:
                raise DataError("pouring-sim: the beads do not fit in the fill tube (scene.fill_tube_height)")
            placed[k] = p
        self.data.qpos[self.bead_qpos:self.bead_qpos + 3 * self.beads] = (placed + self.start).ravel()

    # --- poses --------------------------------------------------------------------------------------------
    def _set_hand(self, pose: Pose) -> None:
        self.data.mocap_pos[self.hand_mocap] = pose.pos
        self.data.mocap_quat[self.hand_mocap] = pose.quat

    def hand_pose(self) -> Pose:
        return Pose(self.data.mocap_pos[self.hand_mocap].copy(), self.data.mocap_quat[self.hand_mocap].copy())

    def container_pose(self) -> Pose:
        """Pose of the container's centre (middle of its axis)."""
        quat = self.data.qpos[3:7].copy()
        return Pose(self.data.qpos[0:3] + quat_mat(quat) @ (Z * self.height / 2), quat)

    def _hand_for(self, centre: Pose) -> Pose:
        """Hand pose that holds the container's centre at `centre` (the grasp's relative pose)."""
        base = centre.pos - quat_mat(centre.quat) @ (Z * self.height / 2)
        quat = quat_mul(centre.quat, quat_inv(self.grasp_quat))
        return Pose(base - quat_mat(quat) @ self.grasp_pos, quat)

    def grasp(self) -> None:
        """Switch the weld on with the current relative pose of container to hand."""
        hand = self.hand_pose()
        rotation = quat_mat(hand.quat)
        self.grasp_pos = rotation.T @ (self.data.qpos[0:3] - hand.pos)
        self.grasp_quat = quat_mul(quat_inv(hand.quat), self.data.qpos[3:7])
        self.model.eq_data[0, 0:3] = 0.0
        self.model.eq_data[0, 3:6] = self.grasp_pos
        self.model.eq_data[0, 6:10] = self.grasp_quat
        self.model.eq_data[0, 10] = 1.0
        self.data.eq_active[0] = 1

    def release(self) -> None:
        self.data.eq_active[0] = 0

    # --- measurement --------------------------------------------------------------------------------------
    def bead_positions(self) -> np.ndarray:
        return self.data.qpos[self.bead_qpos:self.bead_qpos + 3 * self.beads].reshape(-1, 3)

    def bead_counts(self) -> tuple[int, int, int, int]:
        """Beads in the container, in the recipient, in flight and elsewhere."""
        labels = self.config["labels"]
        margin = float(labels["inside_margin"])
        p = self.bead_positions()
        v = self.data.qvel[self.bead_dof:self.bead_dof + 3 * self.beads].reshape(-1, 3)
        base, quat = self.data.qpos[0:3], self.data.qpos[3:7]
        local = (p - base) @ quat_mat(quat)
        in_container = _inside(local, self.radius_in + margin, self.height + margin, margin)
        in_cup = _inside(p - self.cup, float(self.scene["cup_radius"]) + margin,
                         float(self.scene["cup_height"]) + margin, margin) & ~in_container
        flying = (~in_container & ~in_cup & (p[:, 2] > labels["flight_min_height"])
                  & (np.linalg.norm(v, axis=1) > labels["flight_speed"]))
        counts = int(in_container.sum()), int(in_cup.sum()), int(flying.sum())
        return (*counts, self.beads - sum(counts))

    def measure(self) -> np.ndarray:
        """One row of the state (STATE_COLUMNS order)."""
        hand = self.data.mocap_pos[self.hand_mocap]
        base, quat = self.data.qpos[0:3], self.data.qpos[3:7]
        axis = quat_mat(quat)[:, 2]
        centre = base + axis * self.height / 2
        local = quat_mat(quat).T @ (hand - base)
        radial = max(float(np.hypot(local[0], local[1])) - self.radius_out, 0.0)
        vertical = max(-float(local[2]), float(local[2]) - self.height, 0.0)
        row = [*hand, *centre, np.degrees(np.arcsin(np.clip(axis[2], -1, 1))), float(np.hypot(radial, vertical)),
               float(np.linalg.norm((centre - self.cup)[:2])), float(self.data.eq_active[0]), *self.bead_counts()]
        return np.array(row, dtype=np.float64)

    def place_cameras(self, seconds: float) -> None:
        import mujoco

        def spherical(azimuth, elevation, distance):
            a, e = np.radians(azimuth), np.radians(elevation)
            return self.lookat + distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])

        self.model.cam_pos[self.cams["fixed"]] = spherical(*self.fixed_view)
        azimuth, elevation, distance = self.orbit_start
        swing, phase = self.orbit_swing
        self.model.cam_pos[self.cams["orbit"]] = spherical(
            azimuth + self.orbit_rate * seconds, elevation + swing * np.sin(phase + 0.3 * seconds), distance)
        mujoco.mj_camlight(self.model, self.data)

    # --- the script ---------------------------------------------------------------------------------------
    def duration(self, name: str) -> float:
        return _uniform(self.rng, self.config["script"][name]) * float(self.config["time_scale"])

    def _hold(self, seconds: float) -> Iterator[None]:
        for _ in range(max(1, round(seconds / self.frame_seconds))):
            yield

    def _move_hand(self, target: Pose, seconds: float) -> Iterator[None]:
        start = self.hand_pose()
        frames = max(1, round(seconds / self.frame_seconds))
        for f in range(frames):
            def at(s, f=f):
                k = min_jerk((f + s) / frames)
                return Pose(start.pos + k * (target.pos - start.pos), target.quat)
            self._pending = at
            yield

    def _move_container(self, start: Pose, target_pos: np.ndarray, seconds: float) -> Iterator[None]:
        frames = max(1, round(seconds / self.frame_seconds))
        for f in range(frames):
            def at(s, f=f):
                k = min_jerk((f + s) / frames)
                return self._hand_for(Pose(start.pos + k * (target_pos - start.pos), start.quat))
            self._pending = at
            yield

    def _tilt_to(self, centre: Pose, upright: np.ndarray, begin: float, end: float) -> None:
        """Hand motion of one frame tilting the container from `begin` to `end` degrees about its centre."""
        axis = np.cross(Z, self.tilt_dir)

        def at(s):
            angle = begin + s * (end - begin)
            return self._hand_for(Pose(centre.pos, quat_mul(axis_angle_quat(axis, angle), upright)))
        self._pending = at

    def _pour(self, centre: Pose) -> Iterator[None]:
        """Closed-loop pour: fast tilt until beads leave, then slow (paused while many are in flight); once
        (nearly) empty, on to the final tilt, held; then untilt."""
        pour = self.config["pour"]
        upright = centre.quat
        final = 90.0 - _uniform(self.rng, pour["final_elevation"])
        slow = _uniform(self.rng, pour["slow_rate"])
        hold = _uniform(self.rng, pour["final_hold"]) * float(self.config["time_scale"])
        max_frames = round(float(pour["max_seconds"]) * float(self.config["time_scale"]) / self.frame_seconds)
        angle, held, frames = 0.0, 0.0, 0
        while frames < max_frames:
            inside, _, flying, _ = self.bead_counts()
            left = self.beads - inside
            if inside <= int(pour["empty_beads"]):
                rate = 2 * slow
            elif left == 0:
                rate = float(pour["fast_rate"])
            else:
                rate = 0.0 if flying > int(pour["max_in_flight"]) else slow
            new = min(angle + rate * self.frame_seconds, final)
            self._jiggle(bool(inside > int(pour["empty_beads"])))
            self._tilt_to(centre, upright, angle, new)
            angle = new
            frames += 1
            yield
            if angle >= final:
                held += self.frame_seconds
                if held >= hold and (inside <= int(pour["empty_beads"]) or held >= 3 * hold):
                    break
        self._jiggle(False)
        frames = max(1, round(self.duration("untilt") / self.frame_seconds))
        for f in range(frames):
            a0 = angle * (1 - min_jerk(f / frames))
            a1 = angle * (1 - min_jerk((f + 1) / frames))
            self._tilt_to(centre, upright, a0, a1)
            yield

    def _jiggle(self, on: bool) -> None:
        """Small random forces on the beads still in the container (they unjam the stream)."""
        forces = self.data.xfrc_applied[self.bead_bodies]
        forces[:] = 0.0
        if on:
            p = self.bead_positions()
            local = (p - self.data.qpos[0:3]) @ quat_mat(self.data.qpos[3:7])
            inside = _inside(local, self.radius_in, self.height, 0.0)
            forces[inside, :3] = self.rng.normal(0.0, float(self.config["pour"]["jiggle_force"]),
                                                 size=(int(inside.sum()), 3))
        self.data.xfrc_applied[self.bead_bodies] = forces

    def script(self) -> Iterator[None]:
        """Yields once per frame, after setting `self._pending` (hand pose as a function of the fraction of
        the frame elapsed)."""
        lay = self.layout
        hold_pose = self.hand_pose()
        self._pending = lambda s: hold_pose
        yield from self._hold(self.duration("idle_start"))
        # reach the side of the container facing the hand
        base = self.data.qpos[0:3].copy()
        grip = Pose(base + self.grip_dir * self.radius_out + Z * self.height * float(lay["grip_height"]),
                    self._hand_yaw_quat())
        yield from self._move_hand(grip, self.duration("reach"))
        self._pending = lambda s: grip
        self.grasp()
        yield from self._hold(self.duration("grasp"))
        start = self.container_pose()
        carry_z = (float(self.scene["cup_height"]) + _uniform(self.rng, lay["pour_clearance"])
                   + self.height / 2)
        lifted = np.array([start.pos[0], start.pos[1], carry_z - _uniform(self.rng, lay["carry_rise"])])
        yield from self._move_container(start, lifted, self.duration("lift"))
        # the lip over the recipient at the reference tilt
        ref = np.radians(float(lay["pour_reference_tilt"]))
        reach = self.radius_out * np.cos(ref) + self.height / 2 * np.sin(ref) - float(lay["lip_inset"])
        pour_at = self.cup - self.tilt_dir * reach
        pour_at[2] = carry_z
        yield from self._move_container(Pose(lifted, start.quat), pour_at, self.duration("carry"))
        yield from self._pour(Pose(pour_at, start.quat))
        yield from self._move_container(Pose(pour_at, start.quat), lifted, self.duration("carry_back"))
        down = start.pos + Z * float(lay["put_down_height"])
        yield from self._move_container(Pose(lifted, start.quat), down, self.duration("put_down"))
        hand = self.hand_pose()
        self._pending = lambda s: hand
        self.release()
        yield from self._hold(self.duration("release"))
        away = Pose(hand.pos + self.grip_dir * _uniform(self.rng, lay["hand_start_distance"])
                    + Z * _uniform(self.rng, lay["hand_start_height"]), hand.quat)
        yield from self._move_hand(away, self.duration("recede"))
        self._pending = lambda s: away
        yield from self._hold(self.duration("idle_end"))

    def step_frame(self) -> None:
        import mujoco

        for k in range(self.substeps):
            self._set_hand(self._pending((k + 1) / self.substeps))
            mujoco.mj_step(self.model, self.data)

    def settle(self) -> None:
        import mujoco

        steps = round(float(self.config["settle_seconds"]) / float(self.scene["timestep"]))
        mujoco.mj_step(self.model, self.data, nstep=max(steps, 1))
        tube = np.array([mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, f"tube_wall{i}")
                         for i in range(int(self.scene["wall_segments"]))])
        self.model.geom_contype[tube] = 0
        self.model.geom_conaffinity[tube] = 0

    def run(self) -> dict[str, np.ndarray]:
        self.settle()
        limit = int(self.config["episode_length"])
        frames, state, action = [], [], []
        for _ in self.script():
            if len(frames) == limit:
                break
            self.place_cameras(len(frames) * self.frame_seconds)
            frames.append(self.renderer.render())
            state.append(self.measure())
            before = self.hand_pose().pos
            self.step_frame()
            velocity = (self.hand_pose().pos - before) / self.frame_seconds
            action.append([*velocity, float(self.data.eq_active[0])])
        state_array = np.stack(state)
        labels = labels_from_state(state_array, self.frame_seconds, self.config["labels"])
        return {"frames": np.stack(frames, axis=1), "state": state_array,
                "action": np.array(action, dtype=np.float32), "labels": labels}


def _inside(local: np.ndarray, radius: float, height: float, margin: float) -> np.ndarray:
    """Points (in an upright cylinder's frame, origin at its base centre) inside it."""
    radial = np.hypot(local[:, 0], local[:, 1])
    return (radial < radius) & (local[:, 2] > -margin) & (local[:, 2] < height)


def collect_episode(config: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
    """Episode `index` of the simulated pouring dataset `config`; a pure function of (config, index).
    Keys: frames [2, T, H, W, 3] uint8, state [T, 14] (`STATE_COLUMNS`), action [T, 4] float32 (the hand's
    commanded velocity over the next frame in m/s, and 1 while the grasp weld is on during it), labels [T, 9] int8."""
    return PouringEpisode(config, index).run()


__all__ = ["STATE_COLUMNS", "collect_episode"]
