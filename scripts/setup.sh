#!/usr/bin/env bash
# Install gesturedb and everything it needs on a fresh machine (idempotent).
set -euo pipefail
cd "$(dirname "$0")/.."

# VTK's PyPI wheel renders offscreen through EGL but ships no GL driver: it needs
# Debian's EGL loader and Mesa's software rasterizer (see docs/rendering.md).
need=()
for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if ((${#need[@]})); then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}"
fi

python3 -m pip install --quiet --disable-pip-version-check -e ".[test,refiner]"

# Blender as a Python module (bpy, for tests/test_blender.py): it pins numpy < 2 and needs
# Python 3.11, so it gets an environment of its own; where it cannot install, that test skips and says why.
if python3 -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  { [ -x .venv-blender/bin/python ] || python3 -m venv .venv-blender; } &&
    .venv-blender/bin/python -m pip install --quiet --disable-pip-version-check "bpy>=4.2,<6" ||
    echo "setup: bpy did not install; tests/test_blender.py will be skipped" >&2
fi
