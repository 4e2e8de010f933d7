#!/usr/bin/env bash
# Install gesturedb and everything it needs (idempotent): into the active virtual environment,
# else into the project's own .venv (created here), never into the system's Python.
# pip runs only when setup.py, pyproject.toml or csrc/ changed since the last install (a stamp
# file in the environment), so a second run takes a second.
#
# `setup.sh` installs what the product needs (the demo, gesturedb serve); `setup.sh --tests` adds what
# only the test command needs (pytest, the docs tools, torch for the refiner tests, chromium for the studio's).
set -euo pipefail
cd "$(dirname "$0")/.."
for_tests=0
[ "${1:-}" = "--tests" ] && for_tests=1

# VTK's PyPI wheel renders offscreen through EGL but ships no GL driver: it needs
# Debian's EGL loader and Mesa's software rasterizer (see docs/rendering.md).
need=()
# gesturedb serve's studio draws with Debian's three.js (libjs-three); the tests drive it in Debian's
# chromium through chromium-driver (tests/test_studio.py): no browser or script from elsewhere.
pkgs=(libegl1 libegl-mesa0 libgl1-mesa-dri libjs-three)
((for_tests)) && pkgs+=(chromium chromium-driver)
for pkg in "${pkgs[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if ((${#need[@]})); then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}"
fi

. scripts/venv.sh
. scripts/pip_install.sh
if [ ! -x "$GESTUREDB_VENV/bin/python" ]; then
  echo "setup: creating the virtual environment $GESTUREDB_VENV" >&2
  python3 -m venv "$GESTUREDB_VENV"
fi
PY="$GESTUREDB_VENV/bin/python"

# the product's extras (serve); for the tests every extra setup.py declares: the suite exercises them all
extras=serve
((for_tests)) && extras=$("$PY" - <<'PYEOF'
import ast
tree = ast.parse(open("setup.py").read())
for node in ast.walk(tree):
    if isinstance(node, ast.keyword) and node.arg == "extras_require" and isinstance(node.value, ast.Dict):
        print(",".join(sorted(k.value for k in node.value.keys if isinstance(k, ast.Constant))))
        break
PYEOF
)
# what the install depends on: the build files, the C++ sources, the extras and the interpreter
stamp="$GESTUREDB_VENV/.gesturedb-install-stamp"
want=$( { echo "extras=$extras"; "$PY" -c 'import sys; print(sys.version)';
          cat setup.py pyproject.toml; find csrc -type f | LC_ALL=C sort | xargs cat; } | sha256sum | cut -d' ' -f1 )
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && "$PY" -c 'import gesturedb._core' 2>/dev/null; then
  echo "setup: gesturedb is up to date in $GESTUREDB_VENV (nothing changed since the last install)" >&2
else
  # the first time: about 2.6 GB with the test extras (torch 0.75 GB and VTK 0.57 GB are half of it)
  echo "setup: installing gesturedb[$extras] into $GESTUREDB_VENV (the first time up to 2.6 GB, VTK and, for" \
    "the tests, torch the largest, for a few minutes); a line per package pip downloads:" >&2
  rm -f "$stamp"
  pip_install setup "$PY" -e ".${extras:+[$extras]}"
  echo "$want" > "$stamp"
fi
