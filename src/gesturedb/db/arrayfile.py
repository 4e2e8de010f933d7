"""Array files beside a database: a few named arrays, scalar attributes and one large block.

What a stage caches that the database cannot recompute cheaply (the refiner's training
fakes, :mod:`gesturedb.refiner.data`) is stored here rather than by the stage itself, so
that the storage format stays inside :mod:`gesturedb.db`. The file is written through
:func:`gesturedb.db.storage.write_atomically` (a temporary sibling renamed on success); the
block is stored contiguous, so :func:`read` hands it back as a read-only memory map and a
caller never holds it whole in memory.
"""
from __future__ import annotations

import os
from typing import Any, Callable, Mapping

import numpy as np

from gesturedb.db.storage import write_atomically


def write(path: str | os.PathLike, *, attrs: Mapping[str, Any], arrays: Mapping[str, np.ndarray], block: str,
          shape: tuple[int, ...], dtype, fill: Callable[[Any], None]) -> None:
    """Write the array file ``path``: ``attrs``, ``arrays``, then the block ``block`` of ``shape``
    and ``dtype``, which ``fill`` receives (an array-like taking ``out[a:b] = rows``) and fills."""
    def fill_file(h5):
        for k, v in attrs.items():
            h5.attrs[k] = v
        for k, v in arrays.items():
            h5[k] = v
        # contiguous (no chunks, no filters), so that read() can memory-map it
        fill(h5.create_dataset(block, shape=shape, dtype=dtype))

    write_atomically(path, fill_file)


def read_attrs(path: str | os.PathLike) -> dict[str, Any] | None:
    """The scalar attributes of the array file ``path`` (numpy scalars as Python ones, bytes as str),
    or None when there is no such file or it cannot be read."""
    import h5py

    try:
        with h5py.File(os.fspath(path), "r") as h5:
            return {k: _scalar(v) for k, v in h5.attrs.items()}
    except (OSError, KeyError, ValueError):
        return None


def read(path: str | os.PathLike, names, block: str) -> tuple[dict[str, np.ndarray], np.ndarray] | None:
    """The arrays ``names`` (read whole) and the block ``block`` (a read-only memory map, or read
    whole when the file stores it otherwise) of the array file ``path``; None when there is no such
    file, it lacks one of them, or it cannot be read."""
    import h5py

    path = os.fspath(path)
    if not os.path.isfile(path):
        return None
    try:
        with h5py.File(path, "r") as h5:
            arrays = {k: np.asarray(h5[k][()]) for k in names}
            ds = h5[block]
            offset = ds.id.get_offset()
            if offset is None or ds.chunks is not None or ds.compression is not None:  # not contiguous: read it whole
                data = ds[()]
            else:
                data = np.memmap(path, dtype=ds.dtype, mode="r", offset=offset, shape=ds.shape)
    except (OSError, KeyError, ValueError):
        return None
    return arrays, data


def _scalar(v):
    return v.item() if isinstance(v, np.generic) else v.decode() if isinstance(v, bytes) else v
