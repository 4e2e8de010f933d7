"""One exception family for everything gesturedb raises on purpose.

Messages name the file, the field, what was expected and what came, so the CLI
can print them as one line and exit non-zero without a traceback.
"""
from __future__ import annotations

import os


class GestureDBError(Exception):
    """Base of every error gesturedb raises deliberately."""


class ParameterError(GestureDBError, ValueError):
    """A caller passed an argument of the wrong type, shape, dtype or value."""


class InputFileError(GestureDBError):
    """An input file (BVH, npz, WAV, transcript, HDF5) is unreadable or malformed.

    Parameters
    ----------
    path : str or os.PathLike
        The offending file.
    problem : str
        What is wrong, naming the field and the expected and actual values.
    """

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        # builds run recordings in worker processes: keep (path, problem) across pickling
        return (type(self), (self.path, self.problem))


class SchemaError(InputFileError):
    """A database file does not follow the schema this version reads."""


class SearchError(GestureDBError):
    """A search step found no candidate (for example a control mask left nothing)."""


class GestureDBWarning(UserWarning):
    """Something works but is probably not what was meant (the CLI prints it as one line)."""
