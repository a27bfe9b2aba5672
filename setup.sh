#!/usr/bin/env bash
# One command on a fresh machine: system GL libraries for headless rendering (where this user may install
# them), a virtual environment with mftcn-bench and its pinned dependencies, then the default smoke run.
set -euo pipefail
cd "$(dirname "$0")"

GL_PACKAGES="libegl1 libgl1 libegl-mesa0 libgles2 libgl1-mesa-dri"
if ! ldconfig -p 2>/dev/null | grep -q 'libEGL.so.1'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $GL_PACKAGES >/dev/null
  elif command -v sudo >/dev/null && sudo -n true 2>/dev/null && command -v apt-get >/dev/null; then
    sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $GL_PACKAGES >/dev/null
  else
    echo "setup.sh: cannot install system GL libraries here; ask an administrator for: $GL_PACKAGES" >&2
  fi
fi

# The web leaderboard's browser test drives Debian's Chromium through Playwright (whose own browser download
# does not run here); without it that test skips and says why.
if ! command -v chromium >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
  else
    echo "setup.sh: cannot install chromium here; the web leaderboard's browser test will skip" >&2
  fi
fi

PYTHON="${PYTHON:-python3}"
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install --quiet -e ".[dev]"

if [ "${1:-}" != "--no-run" ]; then
  .venv/bin/mftcn-bench run --encoder mftcn4 --task cartpole-probe --preset demo
fi
