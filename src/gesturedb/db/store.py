"""What the database's writers ask of the storage: a handful of operations on an open file.

Writers (the build, the edits, the motion graph, the exports) name datasets by the paths
of :mod:`gesturedb.db.schema` and change a file only through these functions, never
through the HDF5 library: creating a dataset (whole, or growing by rows), setting
attributes, deleting, listing a group. They are written for HDF5 (``h5py``); a second
backend (Zarr, say) implements the same few functions for its own handle, as xarray's
backends each implement one small store interface. The other HDF5-specific code is the
file's life cycle (:mod:`gesturedb.db.storage`: temporary file, lock, rename, compact
copy), opening it for reading (:mod:`gesturedb.db.database`, :mod:`gesturedb.db.schema`'s
checks) and the virtual datasets of an index file (:mod:`gesturedb.db.shardfiles`).

``h5`` below is the writable handle :func:`gesturedb.db.storage.write_atomically` and
:func:`gesturedb.db.storage.edit` give their callers; a ``path`` is ``"group/name"``
(``""``: the file's root).
"""
from __future__ import annotations

import json
from typing import Any, Mapping

import numpy as np


def create(h5, path: str, data: Any = None, *, shape: tuple | None = None, dtype=None,
           chunk_rows: int | None = None, attrs: Mapping[str, Any] | None = None):
    """Create the dataset ``path`` (its groups too) and return it.

    Parameters
    ----------
    data : array-like, optional
        The whole content; or None with ``shape`` and ``dtype`` for an empty dataset.
    chunk_rows : int, optional
        A dataset that grows by rows (:func:`append`): created with ``shape[0]`` rows,
        stored ``chunk_rows`` rows a chunk. Without it the dataset is contiguous (a
        reader may memory-map it).
    attrs : mapping, optional
        Attributes to set (values JSON-encoded by the caller where they are not scalars
        or arrays).
    """
    if chunk_rows is not None:
        shape = tuple(shape)
        ds = h5.create_dataset(path, shape=shape, maxshape=(None,) + shape[1:],
                               chunks=(max(1, int(chunk_rows)),) + shape[1:], dtype=dtype)
    elif data is not None:
        ds = h5.create_dataset(path, data=data, dtype=dtype)
    else:
        ds = h5.create_dataset(path, shape=shape, dtype=dtype)
    for k, v in (attrs or {}).items():
        ds.attrs[k] = v
    return ds


def append(ds, rows: np.ndarray) -> None:
    """Append ``rows`` to a dataset made with ``chunk_rows`` (:func:`create`)."""
    n = ds.shape[0]
    ds.resize(n + rows.shape[0], axis=0)
    ds[n:] = rows


def set_attrs(h5, path: str, attrs: Mapping[str, Any]) -> None:
    """Set attributes of the object at ``path`` (``""``: the root), creating a missing group."""
    obj = h5 if path in ("", "/") else h5[path] if path in h5 else h5.require_group(path)
    for k, v in attrs.items():
        obj.attrs[k] = v


def set_json_attr(h5, path: str, name: str, value: Any) -> None:
    """Set the attribute ``name`` of ``path`` to ``value`` as JSON (keys sorted)."""
    set_attrs(h5, path, {name: json.dumps(value, sort_keys=True)})


def attrs(h5, path: str = "") -> Mapping[str, Any]:
    """The attributes of the object at ``path`` (``""``: the root), read-only by convention."""
    return h5.attrs if path in ("", "/") else h5[path].attrs


def exists(h5, path: str) -> bool:
    """Whether there is an object (dataset or group) at ``path``."""
    return path in h5


def members(h5, group: str) -> list[str]:
    """The names in ``group``, sorted (``[]`` when there is no such group)."""
    g = h5.get(group)
    return [] if g is None else sorted(g)


def array(h5, path: str):
    """The dataset at ``path`` as an array-like read when sliced (``[()]``: whole; ``[a:b]``: rows)."""
    return h5[path]


def delete(h5, path: str) -> None:
    """Delete the object at ``path`` (a group with everything in it); nothing if there is none."""
    if path in h5:
        del h5[path]


def ensure_group(h5, path: str) -> None:
    """Create the group ``path`` if there is none (so that it exists, empty, like a build's)."""
    h5.require_group(path)
