import ctypes

import numpy as np
import pytest

from mftcn_bench.core.errors import DataError, SpecError, SystemRequirementError
from mftcn_bench.data.cartpole import collect_episode
from mftcn_bench.sim import rendering

CONFIG = {"seed": 3, "cameras": ["fixed", "lookatcart"], "height": 24, "width": 32, "episode_length": 12,
          "action_keep_prob": 0.5, "action_repeat": 1, "name": "t",
          "render": {"shadowsize": 16, "offsamples": 0, "shadows": False, "reflection": False},
          "init": {"x_range": 1.0, "x_dot_std": 0.5, "theta_dot_std": 1.0}}


def test_cartpole_episode_is_deterministic_multiview_and_records_state():
    a, b = collect_episode(CONFIG, 0), collect_episode(CONFIG, 0)
    assert a["frames"].shape == (2, 12, 24, 32, 3) and a["frames"].dtype == np.uint8
    assert np.array_equal(a["frames"], b["frames"]) and np.array_equal(a["state"], b["state"])
    assert not np.array_equal(a["frames"][0], a["frames"][1]), "the two cameras see different images"
    assert not np.array_equal(a["state"], collect_episode(CONFIG, 1)["state"])
    assert a["state"].shape == (12, 4) and a["action"].shape == (12, 1)
    assert np.abs(a["action"]).max() <= 1.0
    # positions integrate velocities: x_{t+1} - x_t ~ dt * x_dot (dt = 0.01 s)
    assert np.allclose(np.diff(a["state"][:, 0]), 0.01 * a["state"][1:, 2], atol=0.02)


def test_unknown_camera_names_the_available_ones():
    with pytest.raises(DataError, match="camera 'top' does not exist in this domain; available: fixed, lookatcart"):
        collect_episode({**CONFIG, "cameras": ["fixed", "top"]}, 0)


def test_missing_gl_library_is_one_line_with_the_install_command(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setattr(rendering.ctypes.util, "find_library", lambda name: None)
    with pytest.raises(SystemRequirementError, match="apt-get install -y libegl1") as info:
        rendering.ensure_gl()
    assert "\n" not in str(info.value)


def test_render_settings_turn_the_extra_passes_off_and_keep_the_scene():
    """Shadows and the floor's reflection off change the image (the settings reach the model) while the
    cameras, geometry and sky stay: the same pose renders close to the full-quality frame."""
    lean = collect_episode(CONFIG, 0)["frames"]
    full = collect_episode({**CONFIG, "render": {**CONFIG["render"], "shadows": True, "reflection": True}}, 0)["frames"]
    assert not np.array_equal(lean, full)
    difference = np.abs(lean.astype(np.int16) - full.astype(np.int16))
    assert difference.mean() < 8, "the same scene, without shadows and mirror images"


def test_render_settings_refuse_unknown_keys_in_one_line():
    with pytest.raises(SpecError, match=r"dataset .d.: bad \[render\] table: unknown key\(s\) \[.shadow.\]"):
        rendering.RenderSettings.from_table("dataset 'd'", {"shadowsize": 16, "offsamples": 0, "shadow": False,
                                                            "reflection": False})


def test_a_cuda_device_renders_on_the_egl_device_that_drives_it(monkeypatch):
    """EGL numbers its devices in its own order: the lookup finds the one whose EGL_CUDA_DEVICE_NV is the
    run's GPU (fakes of the two EGL queries), and follow_device hands its index to MuJoCo."""
    devices = ["mesa", "nvidia-1", "nvidia-0"]
    cuda = {"mesa": None, "nvidia-1": 1, "nvidia-0": 0}
    queries = (lambda: devices, lambda device, name: cuda[device] if name == rendering.EGL_CUDA_DEVICE_NV else None)
    assert rendering.egl_device_of_cuda(0, queries) == 2 and rendering.egl_device_of_cuda(1, queries) == 1
    assert rendering.egl_device_of_cuda(2, queries) is None

    def broken():
        raise AttributeError("no eglQueryDevicesEXT")

    assert rendering.egl_device_of_cuda(0, (broken, queries[1])) is None
    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setenv("MUJOCO_EGL_DEVICE_ID", "unset")  # recorded, so the value follow_device sets is undone
    monkeypatch.delenv("MUJOCO_EGL_DEVICE_ID")
    monkeypatch.setattr(rendering, "_egl_device_queries", lambda: queries)
    rendering.follow_device("cuda:1")
    assert rendering.os.environ["MUJOCO_EGL_DEVICE_ID"] == "1"


def test_the_egl_queries_load_here():
    """The real queries resolve on this machine's EGL: the device list is readable; no Mesa device claims a
    CUDA index, and on an NVIDIA machine (the device check) the first GPU's device claims cuda:0."""
    devices, attribute = rendering._egl_device_queries()
    found = devices()
    assert len(found) >= 1
    claimed = [attribute(device, rendering.EGL_CUDA_DEVICE_NV) for device in found]
    if "NVIDIA" in rendering.gl_renderer():
        assert 0 in claimed and rendering.egl_device_of_cuda(0) == claimed.index(0)
    else:
        assert all(index is None for index in claimed)


def test_the_device_attribute_query_reads_an_intptr_through_ctypes():
    """The real ctypes path of eglQueryDeviceAttribEXT against a C callback in its place: the answer comes
    back through an EGLAttrib (intptr_t) out-parameter, and a refusal (EGL_FALSE) reads as None. Mesa refuses
    the attribute, so only this reaches the path an NVIDIA driver takes on a CPU machine."""
    seen = []

    @ctypes.CFUNCTYPE(ctypes.c_uint32, ctypes.c_void_p, ctypes.c_int32, ctypes.POINTER(ctypes.c_ssize_t))
    def fake_query(device, name, value):
        seen.append(name)
        if name != rendering.EGL_CUDA_DEVICE_NV:
            return 0
        value[0] = 3
        return 1

    attribute = rendering.device_attribute_query(ctypes.cast(fake_query, ctypes.c_void_p).value)
    assert attribute(None, rendering.EGL_CUDA_DEVICE_NV) == 3
    assert attribute(None, 0x322C) is None
    assert seen == [rendering.EGL_CUDA_DEVICE_NV, 0x322C]
