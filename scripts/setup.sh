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

python3 -m pip install --quiet --disable-pip-version-check -e ".[test]"
