#!/usr/bin/env bash
# Create or reuse the project's virtual environment in .venv/ and install wfnn into it.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
stamp=.venv/.wfnn-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  # torch is pinned; 2.13.0 CPU is installed explicitly first so nothing pulls another build.
  .venv/bin/python -m pip install --quiet "torch==2.13.0"
  .venv/bin/python -m pip install --quiet -e ".[dev]"
  touch "$stamp"
fi
# Off-screen rendering (HyDrA's rendered vision and camera pictures) needs Mesa's EGL or OSMesa.
# Where it is missing and this script may install Debian packages, it does; otherwise rendering
# is reported unavailable (its tests are skipped with the reason) and everything else works.
if [ ! -f .venv/.wfnn-render-checked ]; then
  if ! .venv/bin/python -m sims.render; then
    if [ "$(id -u)" = 0 ] && command -v apt-get > /dev/null; then
      echo "installing Mesa's off-screen GL (Debian packages) for rendering"
      apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
        libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0 libgl1 libosmesa6 > /dev/null || true
      .venv/bin/python -m sims.render || true
    fi
  fi
  touch .venv/.wfnn-render-checked
fi
