#!/usr/bin/env bash
# Install, then run the whole test suite (unit + end-to-end on ../shared/data).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --tests
bash scripts/blender.sh  # bpy (about 1 GB) for tests/test_blender.py only: demo.sh never downloads it
. scripts/venv.sh  # the environment setup.sh installed into: its pytest, lint-imports and gesturedb
# the layers contract (.importlinter): a stage importing a stage above it fails here
lint-imports --no-cache
ruff check src tests benchmarks  # pyflakes, bugbear and import order (pyproject.toml's [tool.ruff])
clang-format --dry-run --Werror csrc/*.cpp csrc/*.h benchmarks/*.cpp  # the C++ as .clang-format writes it
# the docs site: a broken link, anchor or docstring fails. Not --quiet: it drops the warnings before
# --strict counts them (a broken anchor passed); only the INFO lines are filtered out instead
NO_MKDOCS_2_WARNING=1 mkdocs build --strict --site-dir "$(mktemp -d)" 2>&1 | { grep -v '^INFO' || true; }
exec pytest -q "$@"
