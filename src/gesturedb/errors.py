"""One exception family for everything gesturedb raises on purpose.

Messages name the file, the field, what was expected and what came, so the CLI
can print them as one line and exit non-zero without a traceback.
"""
from __future__ import annotations

import itertools
import os
import reprlib


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


#: characters of a user value that a message quotes; a longer one is cut and its length said
MAX_ECHO_CHARS = 80
#: items of a user list (keys, names) that a message names; the rest are counted
MAX_ECHO_ITEMS = 12

_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = MAX_ECHO_CHARS
_REPR.maxlist = _REPR.maxtuple = _REPR.maxset = _REPR.maxfrozenset = _REPR.maxdict = MAX_ECHO_ITEMS


def echo(value, limit: int = MAX_ECHO_CHARS) -> str:
    """``repr(value)`` for a message, cut to about ``limit`` characters.

    Every message that quotes a user value goes through this (or `echo_list`), so a
    100 MB token, a 125k-character expression or a 2M-key mapping costs a short line,
    never the value itself: ``'abc...' (125000 characters)``.
    """
    if isinstance(value, (str, bytes, bytearray)):
        if len(value) <= limit:
            return repr(value)
        unit = "characters" if isinstance(value, str) else "bytes"
        return f"{value[:limit]!r}... ({len(value)} {unit})"
    text = " ".join(_REPR.repr(value).split())  # one line: numpy's reprs span several
    return text if len(text) <= limit + 3 else text[:limit] + "..."


def echo_list(items, limit: int = MAX_ECHO_ITEMS, *, quote: bool = False) -> str:
    """The first ``limit`` items of a user collection, comma-separated, and how many there are in all.

    Items are `echo`-ed when ``quote``, else printed as text cut to `MAX_ECHO_CHARS`:
    ``a, b, c, ... (2000000 in all)``. Only the shown items are read from an iterator.
    """
    try:
        total = len(items)
    except TypeError:
        total = None
    shown = list(itertools.islice(iter(items), limit + 1))
    more = len(shown) > limit
    shown = shown[:limit]
    if quote:
        parts = [echo(x) for x in shown]
    else:
        parts = [str(x) for x in shown]
        parts = [t if len(t) <= MAX_ECHO_CHARS else f"{t[:MAX_ECHO_CHARS]}... ({len(t)} characters)" for t in parts]
    text = ", ".join(parts)
    if more:
        text += f", ... ({total} in all)" if total is not None else ", ..."
    return text
