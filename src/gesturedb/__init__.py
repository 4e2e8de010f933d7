"""gesturedb: database-driven, controllable co-speech gesture synthesis.

Build a gesture database (HDF5) from recordings of a speaker, then synthesize
gestures for new speech by searching it (Habibie et al. 2022; Zhou et al. 2022).

    db = gesturedb.build(["../shared/data/beat2-scott"], "scott.h5")
    db = gesturedb.open("scott.h5")
"""
from __future__ import annotations

from gesturedb._version import __version__
from gesturedb.errors import (
    GestureDBError,
    InputFileError,
    ParameterError,
    SchemaError,
    SearchError,
)

__all__ = [
    "__version__",
    "GestureDBError",
    "InputFileError",
    "ParameterError",
    "SchemaError",
    "SearchError",
    "Database",
    "build",
    "open",
]


# Bound eagerly: importing the submodule gesturedb.build later would otherwise
# replace the function `gesturedb.build` with the module of the same name.
from gesturedb.db.build import build  # noqa: E402
from gesturedb.db.database import Database  # noqa: E402


def open(path, mode="r"):  # noqa: A001 - mirrors h5py.File / builtins.open on purpose
    """Open a gesture database; see :class:`gesturedb.db.database.Database`."""
    return Database(path, mode=mode)
