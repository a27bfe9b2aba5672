#!/usr/bin/env bash
# One-off: why egl_device_of_cuda(0) is None on the H200, and pixels-cnn's PPO rate at the paper preset on cuda.
set -u; out=$1; here=$(pwd); site=/tmp/mftcn-site
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
python3 -m pip install -q --no-deps --no-index --no-compile --target $site .device-wheels/*.whl
python3 -m pip install -q --no-deps --no-index --no-build-isolation --target $site "$here"
export PYTHONPATH="$site:$here" MFTCN_BENCH_HOME=/tmp/mftcn-home MUJOCO_GL=egl PYTHONUNBUFFERED=1
for t in cheetah swingup; do
  (timeout 230 python3 -m mftcn_bench.cli run --encoder pixels-cnn --task $t --preset paper --device cuda --no-progress > $out/run-$t.txt 2>&1) &
done
timeout 60 python3 - > $out/egl.txt 2>&1 <<'PY'
import ctypes, os, traceback
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
from mftcn_bench.sim import rendering as r
try:
    devices, attribute = r._egl_device_queries()
    ds = devices(); print("devices", len(ds))
    from dm_control._render.pyopengl import egl_ext as EGL
    qs = ctypes.CFUNCTYPE(ctypes.c_char_p, EGL.EGLDeviceEXT, EGL.EGLint)(EGL.eglGetProcAddress("eglQueryDeviceStringEXT"))
    for i, d in enumerate(ds):
        try: print(i, "ext:", qs(d, 0x3055))
        except Exception: traceback.print_exc()
        v = EGL.EGLAttrib(); print(i, "cuda attr:", attribute(d, r.EGL_CUDA_DEVICE_NV), "err", hex(EGL.eglGetError()))
except Exception:
    traceback.print_exc()
print("egl_device_of_cuda(0):", r.egl_device_of_cuda(0))
PY
wait
python3 - > $out/rates.txt 2>&1 <<'PY'
import glob, torch
for p in sorted(glob.glob("/tmp/mftcn-home/**/ppo_checkpoint.pt", recursive=True)):
    s = torch.load(p, weights_only=True, map_location="cpu")["state"]
    print(p); print(" frames", s["curve_frames"]); print(" wall_s", s["curve_wall_s"]); print(" return", s["curve_return"])
PY
nvidia-smi --query-gpu=name,memory.used --format=csv >> $out/rates.txt
cat $out/egl.txt $out/rates.txt; tail -3 $out/run-*.txt
