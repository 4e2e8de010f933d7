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
NO_MKDOCS_2_WARNING=1 mkdocs build --strict --quiet --site-dir "$(mktemp -d)"  # the docs site: a broken link or docstring fails
exec pytest -q "$@"
