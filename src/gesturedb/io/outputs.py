"""Output paths checked before any work: never over an input, never into a missing folder.

Every command calls :func:`check_outputs` first, with all its output paths and
all its input files, so a careless ``-o`` that names the database, a source
recording or the speech fails at once with one line, and nothing (not even the
first of several outputs) is written.
"""
from __future__ import annotations

import os
from typing import Iterable, Mapping

from gesturedb.errors import ParameterError


def _same(a: str, b: str) -> bool:
    if os.path.exists(a) and os.path.exists(b):
        try:
            return os.path.samefile(a, b)
        except OSError:
            pass
    return os.path.realpath(a) == os.path.realpath(b)


def check_outputs(outputs: Mapping[str, str | os.PathLike | None],
                  inputs: Iterable[str | os.PathLike | None] = ()) -> None:
    """Refuse outputs that would overwrite an input, name a folder, or lie in a missing/unwritable folder.

    Parameters
    ----------
    outputs : mapping option -> path
        E.g. ``{"-o": "out.bvh", "--npz": None}``; ``None`` entries are skipped.
    inputs : iterable of paths
        Every file the command reads (database, motion, audio, transcript, rig);
        folders are expanded one level (the files a build would read from them).

    Raises
    ------
    ParameterError
        Naming the option, the path and the problem.
    """
    files: list[str] = []
    for p in inputs:
        if p is None:
            continue
        p = os.fspath(p)
        if os.path.isdir(p):
            for root, _dirs, names in os.walk(p):
                files += [os.path.join(root, n) for n in names]
        else:
            files.append(p)
    seen: dict[str, str] = {}
    for opt, out in outputs.items():
        if out is None:
            continue
        out = os.fspath(out)
        if not out:
            raise ParameterError(f"{opt}: expected a file name, got an empty string")
        if os.path.isdir(out):
            raise ParameterError(f"{opt} {out}: is a folder; expected a file name")
        folder = os.path.dirname(os.path.abspath(out))
        if not os.path.isdir(folder):
            raise ParameterError(f"{opt} {out}: folder {folder} does not exist")
        if not os.access(folder, os.W_OK | os.X_OK) or (os.path.exists(out) and not os.access(out, os.W_OK)):
            raise ParameterError(f"{opt} {out}: not writable (permission denied)")
        for f in files:
            if _same(out, f):
                raise ParameterError(f"{opt} {out}: is an input of this command ({f}); refusing to overwrite it")
        real = os.path.realpath(out)
        if real in seen:
            raise ParameterError(f"{opt} {out}: the same file as {seen[real]}; expected different output files")
        seen[real] = opt
