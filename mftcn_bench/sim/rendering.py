"""Headless rendering with dm_control: the GL check, the render settings and a fast multi-camera renderer.

The suite's default quality (2048 shadow map, 4x multisampling, shadow-casting lights, a reflective floor)
costs 15-20 ms a frame on Mesa's llvmpipe at any size. Each shadow-casting light adds two passes of the
whole scene and a reflective floor one more (MuJoCo's classic renderer); a data set's `[render]` table
turns them off, which brings a 96x48 frame to about 0.6 ms and a 160x160 one to about 1.2 ms with the same
cameras, geometry and sky (docs/PERFORMANCE.md has the measured breakdown).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from mftcn_bench.core.errors import DataError, SystemRequirementError
from mftcn_bench.core.specs import parse_table

GL_PACKAGES = {
    "egl": ("EGL", "apt-get install -y libegl1 libgl1 libegl-mesa0 libgles2 libgl1-mesa-dri"),
    "osmesa": ("OSMesa", "apt-get install -y libosmesa6"),
}


@cache
def gl_renderer() -> str:
    """The GL vendor, renderer and version strings that MuJoCo renders with here (for example
    "Mesa/X.org | llvmpipe (LLVM 15.0.6, 256 bits) | 4.5 (Compatibility Profile) Mesa 22.3.6"), or why
    there is none; one small offscreen context, once per process."""
    try:
        ensure_gl()
        import mujoco

        context = mujoco.GLContext(8, 8)
        try:
            context.make_current()
            from OpenGL import GL

            parts = [GL.glGetString(name) for name in (GL.GL_VENDOR, GL.GL_RENDERER, GL.GL_VERSION)]
        finally:
            context.free()
        return " | ".join((part or b"?").decode(errors="replace") for part in parts)
    except Exception as exc:  # noqa: BLE001 - no GL here: datasets that render fail later with their own line
        return f"unavailable ({type(exc).__name__})"


def follow_device(device: str) -> None:
    """On a GPU run with EGL, render on that GPU: MUJOCO_EGL_DEVICE_ID (unless set) becomes the EGL device
    whose CUDA device is `cuda:N`. EGL numbers its devices in its own order, so the index is looked up
    through EGL_CUDA_DEVICE_NV; where that cannot be read, nothing is set and MuJoCo takes the first EGL
    device that works (on a one-GPU machine, that GPU). Call before MuJoCo makes its first EGL context."""
    if not device.startswith("cuda") or os.environ.get("MUJOCO_GL", "egl") != "egl":
        return
    if "MUJOCO_EGL_DEVICE_ID" in os.environ:
        return
    index = egl_device_of_cuda(int(device.partition(":")[2] or 0))
    if index is not None:
        os.environ["MUJOCO_EGL_DEVICE_ID"] = str(index)


EGL_CUDA_DEVICE_NV = 0x323A

DeviceQueries = tuple[Callable[[], Sequence[object]], Callable[[object, int], int | None]]


def egl_device_of_cuda(cuda_index: int, queries: DeviceQueries | None = None) -> int | None:
    """The EGL device index whose EGL_CUDA_DEVICE_NV is `cuda_index`, or None where EGL or the NVIDIA
    extension cannot say (CPU machines, Mesa). `queries` (the device list and one device's attribute) are
    EGL's by default, in the order MuJoCo indexes MUJOCO_EGL_DEVICE_ID by."""
    try:
        devices, attribute = queries or _egl_device_queries()
        for index, device in enumerate(devices()):
            if attribute(device, EGL_CUDA_DEVICE_NV) == cuda_index:
                return index
    except Exception:  # noqa: BLE001 - no EGL, no extension, another binding: leave MuJoCo's default
        return None
    return None


def _egl_device_queries() -> DeviceQueries:
    """EGL_EXT_device_enumeration and EGL_EXT_device_query through dm_control's EGL wrappers (PyOpenGL's
    `OpenGL.EGL` does not export the two extension functions); raises where EGL lacks them."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from dm_control._render.pyopengl import egl_ext as EGL

    return EGL.eglQueryDevicesEXT, device_attribute_query(EGL.eglGetProcAddress("eglQueryDeviceAttribEXT"),
                                                          EGL.EGLDeviceEXT)


def device_attribute_query(address: Any, device_type: Any = ctypes.c_void_p) -> Callable[[object, int], int | None]:
    """eglQueryDeviceAttribEXT at `address` as (device, attribute) -> its value, or None where the device
    has no such attribute. The value is an EGLAttrib, which EGL defines as intptr_t; PyOpenGL's
    `EGL.EGLAttrib` is a pointer type, which cannot receive it (Mesa refuses the attribute before that shows)."""
    query = ctypes.CFUNCTYPE(ctypes.c_uint32, device_type, ctypes.c_int32, ctypes.POINTER(ctypes.c_ssize_t))(address)

    def attribute(device: object, name: int) -> int | None:
        value = ctypes.c_ssize_t()
        return int(value.value) if query(device, name, ctypes.byref(value)) else None

    return attribute


def ensure_gl() -> str:
    """Select a headless GL backend (MUJOCO_GL, default egl) and check its system library is present."""
    backend = os.environ.setdefault("MUJOCO_GL", "egl")
    if backend in GL_PACKAGES:
        library, install = GL_PACKAGES[backend]
        if ctypes.util.find_library(library) is None:
            raise SystemRequirementError(
                f"headless rendering with MUJOCO_GL={backend} needs the system library lib{library}; "
                f"install it with: {install}"
            )
    return backend


@dataclass(frozen=True)
class RenderSettings:
    """A data set's `[render]` table: how its frames are drawn. Part of the data set's config, so of its id;
    a control task's rollouts draw with its data set's settings (the encoder sees frames like its data)."""

    shadowsize: int    # shadow map size (when lights cast shadows)
    offsamples: int    # multisampling of the offscreen buffer
    # Left out of a table: as the model says (the suite's lights cast shadows, its floor reflects).
    shadows: bool = True      # whether lights cast shadows (two extra passes of the scene per light)
    reflection: bool = True   # whether reflective materials (the suite's floor) mirror the scene (one extra pass)

    @classmethod
    def from_table(cls, owner: str, table: Mapping[str, Any]) -> RenderSettings:
        return parse_table(cls, owner, "render", table)

    def apply(self, model) -> None:
        """Set these on a MuJoCo model before its first render (quality is read when the GL context is made)."""
        model.vis.quality.shadowsize = self.shadowsize
        model.vis.quality.offsamples = self.offsamples
        if not self.shadows:
            model.light_castshadow[:] = 0
        if not self.reflection:
            model.mat_reflectance[:] = 0


class MultiViewRenderer:
    """Renders the same physics state from several named cameras, reusing one camera object each."""

    def __init__(self, physics, cameras: Sequence[str], height: int, width: int,
                 settings: RenderSettings) -> None:
        from dm_control.mujoco.engine import Camera

        available = [physics.model.id2name(i, "camera") for i in range(physics.model.ncam)]
        unknown = [c for c in cameras if c not in available]
        if unknown:
            raise DataError(f"camera {unknown[0]!r} does not exist in this domain; available: "
                            f"{', '.join(available)}")
        settings.apply(physics.model)
        # The offscreen buffer exactly the image size (the suite's is 640x480): the CPU renderer clears and
        # reads the whole buffer each frame, about 1 ms at 96x48; the pixels are identical (tests/test_bench.py).
        physics.model.vis.global_.offwidth, physics.model.vis.global_.offheight = width, height
        self._cameras = [Camera(physics, height, width, camera_id=c) for c in cameras]

    def render(self) -> np.ndarray:
        """uint8 array [views, height, width, 3] of the current state."""
        return np.stack([camera.render() for camera in self._cameras])
