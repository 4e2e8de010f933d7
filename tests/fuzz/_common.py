"""Shared harness of the atheris fuzz targets: bytes -> a temporary file -> a parser.

A target passes when the parser either returns or raises a
:class:`gesturedb.GestureDBError` (the promised one-line error). Any other
exception (IndexError, RecursionError, MemoryError, ...) is a finding: atheris
stops, prints the traceback and writes the input as ``crash-<sha1>``.

Run one target: ``python tests/fuzz/fuzz_bvh.py -max_total_time=60 [CORPUS_DIR]``
(libFuzzer options); all of them: ``scripts/fuzz.sh``.
"""
from __future__ import annotations

import os
import sys
import tempfile

_TMP = tempfile.mkdtemp(prefix="gesturedb-fuzz-")


def tmp_file(data: bytes, suffix: str) -> str:
    """Write ``data`` to the target's one scratch file with ``suffix`` and return its path."""
    path = os.path.join(_TMP, "input" + suffix)
    with open(path, "wb") as f:
        f.write(data)
    return path


def run(test_one_input, seeds: list[bytes]) -> None:
    """Start atheris on ``test_one_input``; ``seeds`` go into a fresh corpus folder unless one is given."""
    import atheris

    argv = list(sys.argv)
    if not any(not a.startswith("-") for a in argv[1:]):
        corpus = tempfile.mkdtemp(prefix="corpus-", dir=_TMP)
        for i, s in enumerate(seeds):
            with open(os.path.join(corpus, f"seed{i}"), "wb") as f:
                f.write(s)
        argv.append(corpus)
    sys.setrecursionlimit(1000)  # as in a plain interpreter: a RecursionError must be found, not hidden
    atheris.Setup(argv, test_one_input)
    atheris.Fuzz()
