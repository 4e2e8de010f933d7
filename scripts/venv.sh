# Sourced by the other scripts: the Python environment gesturedb is installed in.
# An active virtual environment ($VIRTUAL_ENV) is used as it is; otherwise the project's own .venv,
# so the scripts never install into the Python that happens to be first on the PATH.
GESTUREDB_VENV="${VIRTUAL_ENV:-$(pwd)/.venv}"
export PATH="$GESTUREDB_VENV/bin:$PATH"
