"""The stored form of a keyword sub-database: its group layout, reading and writing it, frames of times.

The layer under :mod:`gesturedb.db.keywords` (which finds occurrences, edits and
uses sub-databases): kept apart so each file stays readable on its own. Layout
of ``subdatabases/<word>/`` in :data:`SUBDB_FIELDS`; the module notes of
:mod:`gesturedb.db.keywords` give the matching and timing rules.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gesturedb import control
from gesturedb.db import schema, store
from gesturedb.db.database import Segments
from gesturedb.errors import SchemaError

__all__ = ["SUBDB_FIELDS", "SubDatabase", "time_to_frames", "read_subdb", "read_all", "write_subdb", "mask_of"]

#: Datasets of one sub-database: name -> (dtype, unit, meaning). The group layout is
#: declared here rather than in :data:`gesturedb.db.schema.FIELDS` because its path
#: holds a run-time name (the keyword).
SUBDB_FIELDS: dict[str, tuple[str, str, str]] = {
    "start": ("int64", "frame", "first database frame of each occurrence stretch"),
    "length": ("int64", "frame", "length of each occurrence stretch in frames"),
    "recording": ("int32", "", "index into the recordings table"),
    "word_index": ("int64", "", "index of the keyword occurrence into words/"),
    "mask": ("uint64", "", "union of the stretches: packed bitset over database frames (bit f&63 of word f>>6)"),
}

#: Frames-per-time rounding slack: a word boundary computed as exactly k / fps in
#: floating point (k an integer) must fall on frame k, not k - 1.
EPS_FRAMES = 1e-6


def time_to_frames(start_s, end_s, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Frames covered by time intervals.

    Parameters
    ----------
    start_s, end_s : array-like [shape=(n,)], seconds
    fps : float, Hz

    Returns
    -------
    first, stop : ndarray [shape=(n,)], int64, frames
        Interval ``[start_s, end_s)`` covers frames ``first <= f < stop``, frame
        ``f`` being ``[f / fps, (f + 1) / fps)``; ``stop >= first + 1`` always.
        Not clipped to any recording.
    """
    s = np.atleast_1d(np.asarray(start_s, dtype=np.float64))
    e = np.atleast_1d(np.asarray(end_s, dtype=np.float64))
    first = np.floor(s * fps + EPS_FRAMES).astype(np.int64)
    stop = np.ceil(e * fps - EPS_FRAMES).astype(np.int64)
    return first, np.maximum(stop, first + 1)


@dataclass(frozen=True)
class SubDatabase:
    """A keyword sub-database: the stretches of the database around every occurrence of a word.

    Attributes
    ----------
    word : str
        The keyword, lower case (also the group name in the file).
    start : ndarray [shape=(n,)], int64, frames
        First global database frame of each occurrence stretch.
    length : ndarray [shape=(n,)], int64, frames
    recording : ndarray [shape=(n,)], int32
        Index into the recordings table.
    word_index : ndarray [shape=(n,)], int64
        Index of the occurrence into the database's words table.
    mask : ndarray [shape=(B,)], uint64
        Union of the stretches, packed bitset over database frames.
    definition : dict
        How it was made: ``word``, ``before_s``, ``after_s``, ``matched`` (the word
        forms of the words table that matched), ``found`` (occurrences found),
        ``skipped`` (occurrences outside the motion), ``removed`` (word indices
        taken out with :func:`remove_occurrence`).
    """

    word: str
    start: np.ndarray
    length: np.ndarray
    recording: np.ndarray
    word_index: np.ndarray
    mask: np.ndarray
    definition: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.start.shape[0])

    @property
    def before_s(self) -> float:
        return float(self.definition.get("before_s", float("nan")))

    @property
    def after_s(self) -> float:
        return float(self.definition.get("after_s", float("nan")))

    @property
    def n_frames(self) -> int:
        """Frames in the stretches, counting overlapping stretches twice."""
        return int(self.length.sum())

    def segments(self):
        """The stretches as :class:`gesturedb.db.database.Segments` (e.g. to search the sub-database alone)."""

        return Segments(self.start.copy(), self.length.copy(), self.recording.copy())


def read_subdb(g, word: str, n_frames: int, filename: str) -> SubDatabase:
    arrays = {}
    for name, (dtype, _unit, doc) in SUBDB_FIELDS.items():
        path = f"{schema.SUBDB_GROUP}/{word}/{name}"
        if name not in g:
            raise SchemaError(filename, f"missing dataset {path!r} ({doc})")
        arr = g[name][()]
        if arr.dtype != np.dtype(dtype) or arr.ndim != 1:
            raise SchemaError(filename, f"{path}: expected {dtype} (n,), got {arr.dtype} {arr.shape}")
        arrays[name] = arr
    n = arrays["start"].shape[0]
    for name in ("length", "recording", "word_index"):
        if arrays[name].shape[0] != n:
            raise SchemaError(
                filename,
                f"{schema.SUBDB_GROUP}/{word}/{name}: expected {n} rows (as start), got {arrays[name].shape[0]}",
            )
    nw = control.n_words(n_frames)
    if arrays["mask"].shape[0] != nw:
        raise SchemaError(
            filename,
            f"{schema.SUBDB_GROUP}/{word}/mask: expected {nw} uint64 words for {n_frames} frames, "
            f"got {arrays['mask'].shape[0]}",
        )
    return SubDatabase(
        word=word, start=arrays["start"], length=arrays["length"], recording=arrays["recording"],
        word_index=arrays["word_index"], mask=arrays["mask"],
        definition=schema.read_json_attr(g, "definition", {}),
    )


def read_all(h5, filename: str) -> dict[str, SubDatabase]:
    g = h5.get(schema.SUBDB_GROUP)
    if g is None:
        return {}
    n_frames = int(h5.attrs["n_frames"])
    return {w: read_subdb(g[w], w, n_frames, filename) for w in sorted(g)}


def mask_of(start: np.ndarray, length: np.ndarray, n_frames: int) -> np.ndarray:
    bits = np.zeros(n_frames, dtype=bool)
    for a, n in zip(start, length):
        bits[a:a + n] = True
    return control.pack_bits(bits)


def write_subdb(h5, sub: SubDatabase) -> None:
    """Create ``subdatabases/<word>/`` (replacing an existing one) in an open writable file."""
    group = f"{schema.SUBDB_GROUP}/{sub.word}"
    store.delete(h5, group)
    for name, (dtype, unit, doc) in SUBDB_FIELDS.items():
        store.create(h5, f"{group}/{name}", np.ascontiguousarray(getattr(sub, name), dtype=dtype),
                     attrs={"unit": unit, "doc": doc})
    store.set_json_attr(h5, group, "definition", sub.definition)
