"""A database too big for one file: shard files of whole recordings plus an index file.

``gesturedb shard DB.h5 --parts N`` writes

- N **shard files** ``<index stem>.<token>.<i>-of-<N>.h5``, each holding the per-frame
  arrays (:data:`gesturedb.db.schema.SHARDED_FIELDS`: features, joint positions and
  rotations, ~2 kB of the ~2.1 kB a frame takes) of a contiguous run of whole
  recordings, so a shard can live on its own disk or worker;
- one **index file**, an ordinary database file (same schema) whose per-frame
  arrays are HDF5 virtual datasets over the shards. Everything small (recordings,
  chunks, clips, words, controls, masks, keyword sub-databases, the motion graph)
  stays in the index. ``gesturedb.open(index)`` therefore reads exactly what the
  single file reads, and every command (``synth``, ``eval``, ``keywords`` ...)
  accepts it; ``gesturedb synth --scheduler`` loads each shard file on a worker
  instead of sending the client's copy (:meth:`gesturedb.db.shards.ShardedSearch.from_shard_files`).

Shards hold whole recordings because every segment kind (chunks, clips, keyword
occurrences) lies inside one recording: no segment straddles two files.

Nothing is lost on failure: shard files carry a fresh random token in their names,
so a new sharding never overwrites the files an existing index uses; each file is
written to a temporary file and renamed (:mod:`gesturedb.db.storage`); the index is
renamed last, and only then are the shards of an index it replaced removed. An
interrupted sharding removes the shards it wrote and leaves the previous files as
they were. Opening an index checks that every shard is present and is the part the
index was written with (:func:`gesturedb.db.schema.check_shards`) and that the
index's virtual-dataset mappings name exactly those files (HDF5 would otherwise
read a missing shard as fill values, and a mapping to another file from it); the
open database then reads the shard files it checked and holds open
(:class:`gesturedb.db.database.ShardedArray`), so a re-sharding that removes them
later changes nothing for it. Sharding holds the index's write lock throughout.
"""
from __future__ import annotations

import contextlib
import os
import uuid
from dataclasses import dataclass

import numpy as np

from gesturedb.db import schema, storage
from gesturedb.db.database import Database
from gesturedb.errors import ParameterError

__all__ = ["ShardingReport", "plan_shards", "shard_database", "shard_path"]

#: rows copied per block when writing a shard (bounds memory on a database of any size: ~130 MB)
COPY_ROWS = 1 << 16


@dataclass(frozen=True)
class ShardingReport:
    """What :func:`shard_database` wrote.

    Attributes
    ----------
    index : str
        The index file (open it with :func:`gesturedb.open`).
    shards : list of str
        The shard files, in frame order.
    frames : list of (int, int)
        Each shard's frame range ``[f0, f1)`` in the database.
    recordings : list of (int, int)
        Each shard's recording range ``[r0, r1)``.
    removed : list of str
        Shard files of an index this one replaced, removed after the rename.
    """

    index: str
    shards: list
    frames: list
    recordings: list
    removed: list


def plan_shards(n_frames_per_recording, parts: int) -> list[tuple[int, int]]:
    """Cut recordings into ``parts`` contiguous runs of about equal frame counts.

    Parameters
    ----------
    n_frames_per_recording : array-like of int, shape (R,)
        Frames of each recording, in database order (recordings are stored contiguously).
    parts : int
        1 <= parts <= R.

    Returns
    -------
    list of (int, int)
        Recording ranges ``[r0, r1)``, non-empty, covering 0..R in order.
    """
    n = np.asarray(n_frames_per_recording, dtype=np.int64)
    R = n.shape[0]
    if isinstance(parts, bool) or not isinstance(parts, (int, np.integer)) or not 1 <= parts <= R:
        raise ParameterError(f"parts: expected an int from 1 to {R} (the number of recordings: a shard holds "
                             f"whole recordings), got {parts!r}")
    cum = np.concatenate([[0], np.cumsum(n)])
    cuts = [0]
    for i in range(1, parts):
        target = cum[-1] * i / parts
        # the recording boundary nearest the ideal cut, leaving room for the shards still to come
        r = int(np.clip(np.argmin(np.abs(cum - target)), cuts[-1] + 1, R - (parts - i)))
        cuts.append(r)
    cuts.append(R)
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:])]


def shard_path(index: str, token: str, part: int, parts: int) -> str:
    """The name of shard ``part`` (1-based) of ``parts`` beside ``index``."""
    stem = os.path.splitext(os.path.abspath(index))[0]
    return f"{stem}.{token}.{part}-of-{parts}.h5"


def default_index(path: str) -> str:
    """``DB.h5`` -> ``DB.index.h5`` (beside it)."""
    stem, ext = os.path.splitext(os.fspath(path))
    return f"{stem}.index{ext or '.h5'}"


def shard_database(path, parts: int, *, index=None, progress: bool = False) -> ShardingReport:
    """Split database ``path`` into ``parts`` shard files of whole recordings and an index file.

    Parameters
    ----------
    path : str or os.PathLike
        A database (a single file, or an index: it is re-sharded).
    parts : int
        Number of shard files, 1 to the number of recordings.
    index : str or os.PathLike, optional
        The index file to write (default ``<stem>.index.h5`` beside ``path``). It may be
        ``path`` itself: the file is then replaced by an index once every shard is written.
    progress : bool
        A progress bar over the copied frames (stderr).

    Returns
    -------
    ShardingReport
    """
    import h5py

    path = os.fspath(path)
    index = os.fspath(index) if index is not None else default_index(path)
    # The index's lock for the whole sharding: an edit of the index (masks add ...) made while
    # its frames are copied would otherwise be lost when the new index replaces it, and two
    # re-shardings would each remove only the shards they saw. The source is read through a
    # Database, which holds its shard files open: a re-sharding of the source elsewhere cannot
    # turn what is copied into fill values.
    with storage.locked(index), Database(path) as db:
        rec_ranges = plan_shards([r.n_frames for r in db.recordings], parts)
        starts = [r.start_frame for r in db.recordings]
        n_frames = db.n_frames
        frame_ranges = [(int(starts[a]), int(starts[b]) if b < len(starts) else n_frames) for a, b in rec_ranges]
        token = uuid.uuid4().hex[:8]
        shards = [shard_path(index, token, i + 1, parts) for i in range(parts)]
        old_shards = {e["file"] for e in db.shard_entries}
        if os.path.isfile(index):
            # raw: an index whose shards are already gone still names the files to clean up
            with contextlib.suppress(Exception), h5py.File(index, "r") as h5:
                old_shards |= {e["file"] for e in schema.shard_entries(h5, index)}
        written: list[str] = []
        bar = _bar(progress, n_frames)
        try:
            for i, ((f0, f1), out) in enumerate(zip(frame_ranges, shards)):
                of = {"token": token, "part": i + 1, "parts": parts, "frames": [f0, f1],
                      "index": os.path.basename(index)}
                storage.write_atomically(out, lambda h5, f0=f0, f1=f1, of=of: _fill_shard(h5, db, f0, f1, of, bar))
                written.append(out)
            storage.write_atomically(index, lambda h5: _fill_index(h5, db.h5, shards, frame_ranges, token))
        except BaseException:
            for f in written:
                with contextlib.suppress(OSError):
                    os.unlink(f)
            raise
        finally:
            if bar is not None:
                bar.close()
        removed = []
        for f in sorted(old_shards):
            if f not in shards and os.path.isfile(f):
                with contextlib.suppress(OSError):
                    os.unlink(f)
                    removed.append(f)
    return ShardingReport(index=index, shards=shards, frames=frame_ranges, recordings=rec_ranges, removed=removed)


def _bar(progress, total):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", desc="shard", leave=False)


def _fill_shard(h5, db, f0: int, f1: int, of: dict, bar) -> None:
    src = db.h5
    schema.write_json_attr(h5, schema.SHARD_OF_ATTR, of)
    h5.attrs["gesturedb_version"] = src.attrs.get("gesturedb_version", "?")
    for p in schema.SHARDED_FIELDS:
        if p not in src:
            continue
        s = db.frame_source(p)  # of a sharded source, its open shard files (not the virtual dataset)
        d = h5.create_dataset(p, shape=(f1 - f0,) + s.shape[1:], dtype=s.dtype)
        for k, v in s.attrs.items():
            if k != schema.MEAN_ATTR:  # the whole database's, not this part's (the index keeps it)
                d.attrs[k] = v
        for a in range(f0, f1, COPY_ROWS):
            b = min(a + COPY_ROWS, f1)
            d[a - f0:b - f0] = s[a:b]
    if bar is not None:
        bar.update(f1 - f0)


def _fill_index(h5, src, shards: list[str], frame_ranges: list, token: str) -> None:
    import h5py

    for k, v in src.attrs.items():
        if k != schema.SHARDS_ATTR:
            h5.attrs[k] = v
    schema.write_json_attr(h5, schema.SHARDS_ATTR, [
        {"file": os.path.basename(f), "frames": [int(a), int(b)], "token": token}
        for f, (a, b) in zip(shards, frame_ranges)])
    for name in src:
        if name != schema.FRAMES:
            src.copy(src[name], h5, name)
    frames = h5.require_group(schema.FRAMES)
    for k, v in src[schema.FRAMES].attrs.items():
        frames.attrs[k] = v
    for name, s in src[schema.FRAMES].items():
        p = f"{schema.FRAMES}/{name}"
        if p not in schema.SHARDED_FIELDS:
            src.copy(s, frames, name)
            continue
        layout = h5py.VirtualLayout(shape=s.shape, dtype=s.dtype)
        for f, (a, b) in zip(shards, frame_ranges):
            # the shard's name only: HDF5 looks for it beside the index, so the set can be moved together
            layout[a:b] = h5py.VirtualSource(os.path.basename(f), p, shape=(b - a,) + s.shape[1:])
        d = h5.create_virtual_dataset(p, layout, fillvalue=None)
        for k, v in s.attrs.items():
            d.attrs[k] = v


def describe(report: ShardingReport) -> str:
    """One line per file for the CLI."""
    lines = [f"wrote {report.index}: index of {len(report.shards)} shard(s)"]
    for f, (a, b), (r0, r1) in zip(report.shards, report.frames, report.recordings):
        lines.append(f"  {os.path.basename(f)}: frames {a}..{b} ({b - a}), recordings {r0}..{r1 - 1}")
    if report.removed:
        lines.append(f"  removed {len(report.removed)} shard file(s) of the index it replaced")
    return "\n".join(lines)
