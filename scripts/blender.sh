#!/usr/bin/env bash
# Blender as a Python module (bpy, about 1 GB) for tests/test_blender.py, the only thing that needs it.
# scripts/test.sh (the test command, which CI runs) calls this; setup.sh and demo.sh never do, so a
# first demo does not download it. bpy pins numpy < 2 and needs Python 3.11, so it gets an environment
# of its own, .venv-blender. Where it cannot install this says why and succeeds: the test then skips
# and says why too. GESTUREDB_BLENDER_PYTHON names another interpreter that has bpy (nothing installed).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/pip_install.sh
venv=.venv-blender

if [ -n "${GESTUREDB_BLENDER_PYTHON:-}" ]; then
  echo "blender: using $GESTUREDB_BLENDER_PYTHON (GESTUREDB_BLENDER_PYTHON); nothing to install" >&2
  exit 0
fi
if ! python3 -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
  echo "blender: bpy needs Python 3.11, python3 is $(python3 -c 'import sys; print(sys.version.split()[0])');" \
    "tests/test_blender.py will be skipped" >&2
  exit 0
fi
if [ -x "$venv/bin/python" ] && "$venv/bin/python" -c 'import bpy' 2>/dev/null; then
  exit 0  # installed already: a second run takes a second
fi
echo "blender: installing bpy (about 1 GB) into $venv for tests/test_blender.py; a line per package pip downloads:" >&2
if ! { [ -x "$venv/bin/python" ] || python3 -m venv "$venv"; } || ! pip_install blender "$venv/bin/python" "bpy>=4.2,<6"
then
  echo "blender: bpy did not install; tests/test_blender.py will be skipped" >&2
fi
