"""The read floors of bench_search.py, built on demand from floors.cpp.

They are benchmark code, so gesturedb._core does not ship them: ``load()``
compiles ``benchmarks/floors.cpp`` (with ``csrc/threads.cpp`` for the default
thread count) into ``benchmarks/build/`` with the core's flags the first time
the sources change, and calls it through ctypes::

    from floors import load
    floors = load()
    floors.stream_sum_f32(pose, 2)            # read once on 2 threads
    floors.gather_sum_f32(audio, starts, 8)   # rows [s, s + 8) for each s

Needs a C++17 compiler (``$CXX``, else ``c++``), the one that builds the package.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SOURCES = (HERE / "floors.cpp", ROOT / "csrc" / "threads.cpp")
HEADERS = tuple(ROOT / "csrc" / h for h in ("pool.h", "prefetch.h", "threads.h"))
# the baseline flags of gesturedb._core (setup.py): no -march=native, no -ffast-math
FLAGS = ("-O3", "-fno-math-errno", "-pthread", "-std=c++17", "-shared", "-fPIC")


def _compiler() -> str:
    cxx = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if not cxx:
        raise RuntimeError("floors: expected a C++17 compiler ($CXX, c++ or g++); found none on the PATH")
    return cxx


def _library() -> Path:
    """The compiled floors, rebuilt when a source, a header, the flags or the compiler changes."""
    cxx = _compiler()
    h = hashlib.sha256(" ".join((cxx,) + FLAGS).encode())
    for f in SOURCES + HEADERS:
        h.update(f.read_bytes())
    out = HERE / "build" / f"floors-{h.hexdigest()[:16]}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    # built beside its final name and renamed: a second process never loads half a file
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        cmd = [cxx, *FLAGS, f"-I{ROOT / 'csrc'}", *map(str, SOURCES), "-o", tmp]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"floors: compiling {SOURCES[0].name} failed ({' '.join(cmd)}):\n{res.stderr}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


class Floors:
    """ctypes face of floors.cpp: checks the arrays, then calls the C entry points."""

    def __init__(self, path: Path):
        self._lib = lib = ctypes.CDLL(str(path))
        i64, c_int, ptr = ctypes.c_int64, ctypes.c_int, ctypes.c_void_p
        out = (ctypes.POINTER(ctypes.c_double), ctypes.c_char_p, i64)
        lib.gesturedb_stream_sum_f32.argtypes = (ptr, i64, c_int) + out
        lib.gesturedb_gather_sum_f32.argtypes = (ptr, i64, i64, ptr, i64, i64, c_int) + out
        lib.gesturedb_stream_sum_f32.restype = lib.gesturedb_gather_sum_f32.restype = c_int

    @staticmethod
    def _f32(a, name):
        if not isinstance(a, np.ndarray) or a.dtype != np.float32 or not a.flags.c_contiguous:
            got = f"{a.dtype} {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
            raise TypeError(f"{name}: expected a float32 C-contiguous array; got {got}")
        return a

    @staticmethod
    def _call(fn, *args):
        s, err = ctypes.c_double(), ctypes.create_string_buffer(512)
        if fn(*args, ctypes.byref(s), err, len(err)) != 0:
            raise ValueError(err.value.decode())
        return s.value

    def stream_sum_f32(self, a, threads: int = 0) -> float:
        """Sum of a float32 array read once by `threads` threads (0: the default count): the
        memory-bandwidth floor of any kernel that must read the same bytes."""
        a = self._f32(a, "a")
        return self._call(self._lib.gesturedb_stream_sum_f32, a.ctypes.data, a.size, threads)

    def gather_sum_f32(self, a, starts, rows_each: int, threads: int = 0) -> float:
        """Sum of rows [s, s + rows_each) of a (rows, cols) float32 array for every s in starts,
        read in parallel with the step's prefetching: the floor of a scattered pass that reads
        one window per segment."""
        a = self._f32(a, "a")
        if a.ndim != 2:
            raise ValueError(f"a: expected a 2-D array; got shape {a.shape}")
        if (not isinstance(starts, np.ndarray) or starts.dtype != np.int64 or starts.ndim != 1
                or not starts.flags.c_contiguous):
            raise ValueError("starts: expected a 1-D int64 C-contiguous array")
        if rows_each < 1:
            raise ValueError(f"rows_each: expected >= 1; got {rows_each}")
        return self._call(self._lib.gesturedb_gather_sum_f32, a.ctypes.data, a.shape[0], a.shape[1],
                          starts.ctypes.data, starts.shape[0], rows_each, threads)


_loaded: Floors | None = None


def load() -> Floors:
    """The floors, compiled on first use (a few seconds) and then loaded from benchmarks/build/."""
    global _loaded
    if _loaded is None:
        _loaded = Floors(_library())
    return _loaded
