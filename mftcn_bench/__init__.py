"""mftcn-bench: benchmark suite and evaluation harness for learned visual representations for control."""

import os
from importlib.metadata import PackageNotFoundError, version

# MuJoCo picks its GL backend when it is first imported, and torchrl imports it with its environments; the
# harness renders headless (EGL unless the user chose otherwise), so the choice is made before any module
# of the harness can import either (`sim.rendering.ensure_gl` checks its system library before rendering).
os.environ.setdefault("MUJOCO_GL", "egl")

try:
    __version__ = version("mftcn-bench")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
