"""Reading a gesture database: what :func:`gesturedb.open` returns.

Arrays are read on first use and kept (a 616k-frame database holds about 240 MB
of pose features); per-frame arrays come back float32 C-contiguous so they can
be handed to the search kernel without a copy. A per-frame array stored
contiguous and unfiltered in the database file (what builds and edits write) is
not read but memory-mapped, read-only, from the open file (:meth:`Database._mapped`):
the same bits, with the pages read as they are used; chunked, compressed,
virtual (an index file's) or external datasets are read as before. :meth:`Database.rows` and
:meth:`Database.frame_mean` read a per-frame array's rows without loading it,
for a client of a database larger than its memory (a sharded search reads the
frames on the workers; the client needs only the chosen windows).

An index file (``gesturedb shard``) is opened with its shard files: each is
checked (it is the part the index was written with, and the index's
virtual-dataset mappings name exactly it) and kept open, and the per-frame
arrays are read from those open files rather than through HDF5's virtual
datasets, which look the shards up by name at every read. A re-sharding that
replaces the index and removes the old shards while a reader has it open
therefore changes nothing for that reader (POSIX keeps a removed file readable
while it is open), where the virtual datasets read fill values (zeros) for the
removed files; and a shard swapped for another file after the check is never
read.
"""
from __future__ import annotations

import functools
import mmap
import os
import sys
from dataclasses import dataclass

import numpy as np

from gesturedb.db import schema
from gesturedb.errors import InputFileError, ParameterError, SchemaError
from gesturedb.motion import Motion, Skeleton

#: times an open retries when the index it opened was replaced (re-sharded) while it checked its shards
OPEN_TRIES = 5


class ShardedArray:
    """A per-frame dataset of an index file, read from the shard files the database holds open.

    Quacks like the h5py dataset it stands for where the database reads one: ``shape``,
    ``dtype``, ``ndim``, ``attrs`` (the index's), and ``[a:b]`` / ``[a:b, column]`` /
    ``[()]`` reads that come back as one array, whatever shards they span.
    """

    def __init__(self, index_ds, parts: list):
        self.shape = tuple(index_ds.shape)
        self.dtype = index_ds.dtype
        self.ndim = len(self.shape)
        self.attrs = index_ds.attrs
        self._parts = parts  # [(f0, f1, shard dataset)] in frame order

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key):
        rest: tuple = ()
        if isinstance(key, tuple):
            key, rest = (key[0], key[1:]) if key else (slice(None), ())
        if key is Ellipsis:
            key = slice(None)
        if not isinstance(key, slice):
            raise TypeError(f"ShardedArray: expected a slice of rows, got {key!r}")
        a, b, step = key.indices(self.shape[0])
        if step != 1:
            raise TypeError(f"ShardedArray: expected a slice with step 1, got {key!r}")
        pieces = [ds[(slice(max(a, f0) - f0, min(b, f1) - f0),) + rest]
                  for f0, f1, ds in self._parts if max(a, f0) < min(b, f1)]
        if not pieces:
            return self._parts[0][2][(slice(0, 0),) + rest]
        return pieces[0] if len(pieces) == 1 else np.concatenate(pieces)


@dataclass(frozen=True)
class Recording:
    """One row of the recordings table."""

    index: int
    name: str
    speaker: str
    start_frame: int
    n_frames: int
    duration_s: float
    source_fps: float
    mirrored: bool
    motion_path: str
    audio_path: str
    transcript_path: str

    @property
    def stop_frame(self) -> int:
        return self.start_frame + self.n_frames


@dataclass(frozen=True)
class Segments:
    """Segments over database frames: `[start[i], start[i] + length[i])`.

    start, length : ndarray [shape=(M,)], int64, frames
    recording : ndarray [shape=(M,)], int32, index into the recordings table
    """

    start: np.ndarray
    length: np.ndarray
    recording: np.ndarray

    def __len__(self) -> int:
        return int(self.start.shape[0])


@dataclass(frozen=True)
class Clips(Segments):
    """Word-gap clips (GestureMaster) with their signatures.

    word_start, word_end : ndarray [shape=(K,)], int64, index range into :attr:`Database.words`
    rhythm_audio, rhythm_motion : ndarray [shape=(K,)], uint32, bin 0 = least significant bit
    style : ndarray [shape=(K, 3)], float32: mean hand speed (m/s), radius (m), height (m)
    """

    word_start: np.ndarray = None
    word_end: np.ndarray = None
    rhythm_audio: np.ndarray = None
    rhythm_motion: np.ndarray = None
    style: np.ndarray = None


@dataclass(frozen=True)
class WordTable:
    """Words of all recordings; times relative to their recording (s)."""

    recording: np.ndarray
    start_s: np.ndarray
    end_s: np.ndarray
    text: list

    def __len__(self) -> int:
        return len(self.text)


class Database:
    """An open gesture database (HDF5, see :mod:`gesturedb.db.schema`).

    Parameters
    ----------
    path : str or os.PathLike
    mode : {"r"}
        Databases are opened read-only; edits (masks, keyword sub-databases)
        go through :mod:`gesturedb.db.storage`, which rewrites the file atomically.
    """

    def __init__(self, path, mode: str = "r"):
        if mode != "r":
            raise ParameterError(f"mode: expected 'r', got {mode!r} (edit databases through gesturedb.db.storage)")
        self.path = os.fspath(path)
        #: per-frame arrays stored contiguous are memory-mapped (:meth:`_mapped`); GESTUREDB_MMAP=0 reads them
        self.map_frames = os.environ.get("GESTUREDB_MMAP", "1") != "0"
        self._shard_files: list = []
        for attempt in range(OPEN_TRIES):
            ino = _inode(self.path)
            if ino is None:
                raise InputFileError(self.path, "no such file")
            try:
                self._open()
                return
            except SchemaError:
                # a re-sharding replaced the index (and removed the shards it named) while this
                # one checked them: open the new index, as a reader that came a moment later would
                if attempt + 1 < OPEN_TRIES and _inode(self.path) not in (ino, None):
                    continue
                raise

    def _open(self) -> None:
        import h5py

        self._check_maps: dict = {}  # path -> the check's memory map, until the attribute takes it (per attempt)
        try:
            self._h5 = h5py.File(self.path, "r")
        except OSError as exc:
            raise InputFileError(self.path, f"not an HDF5 file ({exc})") from None
        try:
            try:
                schema.check_file(self._h5, self.path, sample=self._check_rows)
            except OSError as exc:  # HDF5 reading a shard that vanished under the check's sampled rows
                raise SchemaError(self.path, f"cannot read while checking the file: {exc}") from None
            self._shard_files = self._open_shards()
        except BaseException:
            self.close()
            raise

    def _open_shards(self) -> list:
        """Open every shard file of an index and check the open file (not only its name) is the right part."""
        import h5py

        entries = schema.shard_entries(self._h5, self.path)
        _allow_open_files(len(entries))
        files = []
        try:
            for i, e in enumerate(entries):
                where = f"{schema.SHARDS_ATTR}[{i}] ({os.path.basename(e['file'])})"
                try:
                    f = h5py.File(e["file"], "r")
                except OSError as exc:
                    raise SchemaError(self.path, f"{where}: cannot open the shard file {e['file']} "
                                                 f"({exc.strerror or exc})") from None
                files.append(f)
                want = schema.shard_expected(entries, i)
                try:
                    of = schema.read_json_attr(f, schema.SHARD_OF_ATTR, None)
                except (TypeError, ValueError):
                    of = None
                got = {k: (of if isinstance(of, dict) else {}).get(k) for k in want}
                if got != want:
                    raise SchemaError(self.path, f"{where}: expected the shard {want} of this index, got {got} in "
                                                 f"{e['file']} (the file changed after it was checked)")
                n = e["frames"][1] - e["frames"][0]
                for p in schema.SHARDED_FIELDS:
                    if p in self._h5 and (p not in f or f[p].shape != (n,) + self._h5[p].shape[1:]):
                        raise SchemaError(self.path, f"{where}: {p}: expected shape {(n,) + self._h5[p].shape[1:]}, "
                                                     f"got {f[p].shape if p in f else 'no dataset'}")
            return [(e["frames"][0], e["frames"][1], f) for e, f in zip(entries, files)]
        except BaseException:
            for f in files:
                f.close()
            raise

    # -- lifetime -------------------------------------------------------------
    def close(self) -> None:
        for _, _, f in self._shard_files:
            f.close()
        self._shard_files = []
        if getattr(self, "_h5", None) is not None:
            self._h5.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __repr__(self) -> str:
        return f"<gesturedb.Database {self.path!r}: {self.n_frames} frames at {self.fps:g} fps, {len(self.recordings)} recordings>"

    # -- scalars --------------------------------------------------------------
    @property
    def h5(self):
        """The underlying read-only :class:`h5py.File`, for the modules of :mod:`gesturedb.db` only.

        Other stages ask the database (:meth:`read`, :meth:`frame_shape`, :meth:`motion_graph`,
        ...), so that the storage stays swappable (``tests/test_architecture.py`` checks it)."""
        return self._h5

    # cached: the file is open read-only, and reading an HDF5 attribute costs ~50 us, which the
    # synthesis paid 345 times per minute of output (9% of its time)
    @functools.cached_property
    def fps(self) -> float:
        return float(self._h5.attrs["fps"])

    @functools.cached_property
    def n_frames(self) -> int:
        return int(self._h5.attrs["n_frames"])

    @functools.cached_property
    def config(self) -> dict:
        """The build configuration the database was made with."""
        return schema.read_json_attr(self._h5, "config", {})

    @functools.cached_property
    def motion_timescale_s(self) -> float | None:
        """The arms' motion timescale (s) the build measured (features.pose.motion_timescale); None before it did."""
        value = self._h5.attrs.get("motion_timescale_s")
        return None if value is None else float(value)

    @functools.cached_property
    def feature_joints(self) -> dict:
        """role -> joint name used for the features."""
        return schema.read_json_attr(self._h5, "feature_joints", {})

    @functools.cached_property
    def shard_entries(self) -> list[dict]:
        """The shard files of an index file (``gesturedb shard``), ``[]`` for a single-file database.

        Each entry: ``{"file": absolute path, "frames": (f0, f1), "token": str}``, in frame order.
        """
        return schema.shard_entries(self._h5, self.path)

    @property
    def sample_rate(self) -> int:
        """Audio sample rate (Hz) the features were computed at: speech for this database is read at it."""
        return int(self.config.get("sample_rate", schema.DEFAULT_SAMPLE_RATE))

    @property
    def gesturedb_version(self) -> str:
        return str(self._h5.attrs.get("gesturedb_version", "?"))

    def _read(self, path: str) -> np.ndarray:
        return schema.read(self._h5, path)

    def read(self, path: str) -> np.ndarray:
        """A declared dataset (a path of :mod:`gesturedb.db.schema`, e.g. ``schema.SKELETON_NAMES``),
        read whole: an array of the declared dtype, or a list of str."""
        return self._read(path)

    def has(self, path: str) -> bool:
        """Whether the file holds a dataset or group at ``path`` (a schema path or group)."""
        return path in self._h5

    def frame_source(self, path: str):
        """The per-frame dataset at ``path`` (``"frames/pose_features"`` ...) to read rows from.

        An h5py dataset of a single-file database; for an index, a :class:`ShardedArray`
        over the shard files this database holds open (see the module notes).
        """
        if path not in self._h5:
            field = schema.FIELDS_BY_PATH.get(path)
            raise SchemaError(self.path, f"missing dataset {path!r}" + (f" ({field.doc})" if field else ""))
        ds = self._h5[path]
        if self._shard_files and path in schema.SHARDED_FIELDS:
            return ShardedArray(ds, [(f0, f1, f[path]) for f0, f1, f in self._shard_files])
        return ds

    def _frames(self, path: str) -> np.ndarray:
        if self._shard_files and path in schema.SHARDED_FIELDS:
            src = self.frame_source(path)
            want = np.dtype(schema.FIELDS_BY_PATH[path].dtype)
            if src.dtype != want:
                raise SchemaError(self.path, f"{path}: expected dtype {want}, got {src.dtype}")
            arr = src[()]
        else:
            arr = self._mapped(path)
            if arr is None:
                arr = self._read(path)
        arr = np.ascontiguousarray(arr)
        if arr.shape[0] != self.n_frames:
            raise SchemaError(self.path, f"{path}: expected {self.n_frames} frames, got {arr.shape[0]}")
        arr.setflags(write=False)
        return arr

    def _mapped(self, path: str) -> np.ndarray | None:
        """The dataset at ``path`` as a read-only array over a memory map of the open file, or None
        where it must be read instead (see :func:`mappable`).

        A 616k-frame database's per-frame arrays are about 1.2 GB: reading them took 3.5 s before
        the first step of a synthesis; mapped, the pages are read as the search touches them.
        The map is of the file HDF5 holds open (its inode), not of whatever has the name now: databases are
        replaced by writing a new file and renaming it over the old one (:mod:`gesturedb.db.storage`;
        edits, ``masks``, ``keywords``, ``graph`` and builds alike), so a map of the old inode stays
        valid and unchanged while it is used, as the open HDF5 file does, and a file renamed in
        between is never mixed in. Nothing writes a database file in place, and the map is
        read-only (``PROT_READ``): an array from it can neither be written through nor go stale.
        """
        ds = self._h5.get(path)
        if not self.map_frames or ds is None or not mappable(ds, self._h5):
            return None
        if path in self._check_maps:  # the map the open's check made: the same bytes, mapped once
            return self._check_maps.pop(path)
        fd = _open_same_file(self._h5.id.get_vfd_handle(), self.path)
        if fd is None:
            return None
        offset = int(ds.id.get_offset())
        base = offset - offset % mmap.ALLOCATIONGRANULARITY
        try:
            # the map keeps the file (a descriptor of its own): the array outlives close() of the database
            mm = mmap.mmap(fd, offset - base + ds.nbytes, access=mmap.ACCESS_READ, offset=base)
        finally:
            os.close(fd)
        arr = np.frombuffer(mm, dtype=ds.dtype, count=int(np.prod(ds.shape, dtype=np.int64)), offset=offset - base)
        want = np.dtype(schema.FIELDS_BY_PATH[path].dtype)
        if arr.dtype != want:
            raise SchemaError(self.path, f"{path}: expected dtype {want}, got {arr.dtype}")
        return arr.reshape(ds.shape)

    # -- per-frame arrays -----------------------------------------------------
    #: attribute -> dataset of the per-frame arrays :meth:`rows` reads
    FRAME_ARRAYS = {"pose_features": schema.POSE_FEATURES, "audio_features": schema.AUDIO_FEATURES,
                    "audio_deltas": schema.AUDIO_DELTAS, "joint_positions": schema.JOINT_POSITIONS,
                    "local_rotations": schema.LOCAL_ROTATIONS, "root_positions": schema.ROOT_POSITIONS,
                    "frame_recording": schema.FRAME_RECORDING}

    def _check_rows(self, path: str, rows: np.ndarray) -> np.ndarray:
        """``schema.check_file``'s sampled rows of a per-frame array, from its memory map (read through h5py
        where it is not mappable), kept until the array's attribute takes it (:meth:`_mapped`): each array is
        mapped once and the check reads the bytes the search will (milliseconds against h5py's 0.08-0.27 s at
        616k frames); the attribute stays unset till used, so ``map_frames = False`` after the open reads."""
        name = next((k for k, v in self.FRAME_ARRAYS.items() if v == path), None)
        ds = self._h5.get(path)
        if (name is None or ds is None or not self.map_frames or schema.SHARDS_ATTR in self._h5.attrs
                or ds.dtype != np.dtype(schema.FIELDS_BY_PATH[path].dtype) or not mappable(ds, self._h5)):
            return self._h5[path][rows]
        arr = self.__dict__.get(name, self._check_maps.get(path))
        if arr is None:
            arr = self._check_maps[path] = self._mapped(path)
        return self._h5[path][rows] if arr is None else arr[rows]

    def _frame_dataset(self, name: str):
        """The h5py dataset of a per-frame array, checked once against the schema (dtype, F rows)."""
        path = self.FRAME_ARRAYS.get(name)
        if path is None:
            raise ParameterError(f"name: expected one of {sorted(self.FRAME_ARRAYS)}, got {name!r}")
        cache = self.__dict__.setdefault("_frame_datasets", {})
        if path not in cache:
            ds = self.frame_source(path)
            want = np.dtype(schema.FIELDS_BY_PATH[path].dtype)
            if ds.dtype != want:
                raise SchemaError(self.path, f"{path}: expected dtype {want}, got {ds.dtype}")
            if ds.ndim < 1 or ds.shape[0] != self.n_frames:
                raise SchemaError(self.path, f"{path}: expected {self.n_frames} frames, got shape {ds.shape}")
            cache[path] = ds
        return cache[path]

    def frame_shape(self, name: str) -> tuple[int, ...]:
        """The shape of a per-frame array (a key of :attr:`FRAME_ARRAYS`), read from the file without
        loading the array: ``(F, Dp)`` for ``"pose_features"``, ``(F, J, 4)`` for ``"local_rotations"``."""
        return tuple(int(n) for n in self._frame_dataset(name).shape)

    def rows(self, name: str, frames, *, column: int | None = None) -> np.ndarray:
        """Rows of a per-frame array at database frames, without loading the whole array.

        Parameters
        ----------
        name : str
            A per-frame attribute (a key of :attr:`FRAME_ARRAYS`: ``"pose_features"``,
            ``"local_rotations"``, ``"root_positions"``, ...).
        frames : array-like of int [shape=(n,)]
            Global frame indices in ``0..F-1``, in any order, repeats allowed.
        column : int, optional
            Only this index of the second axis (e.g. ``0``: the root joint of
            ``local_rotations``), read as a strided selection.

        Returns
        -------
        ndarray [shape=(n, ...)], the array's dtype
            ``getattr(db, name)[frames]`` (``[frames, column]``), bit for bit. The
            loaded or memory-mapped array is indexed when there is one; otherwise each run of
            consecutive frames is one read from the file (through an index
            file, from its shard files).
        """
        frames = np.asarray(frames)
        if frames.ndim != 1 or not (frames.size == 0 or frames.dtype.kind in "iu"):  # integers (not bool)
            raise ParameterError(f"frames: expected a 1-D array of frame indices, got shape {frames.shape} "
                                 f"dtype {frames.dtype}")
        frames = frames.astype(np.int64, copy=False)
        F = self.n_frames
        if frames.size and (int(frames.min()) < 0 or int(frames.max()) >= F):
            bad = int(frames[(frames < 0) | (frames >= F)][0])
            raise ParameterError(f"frames: expected indices in 0..{F - 1} ({self.path}), got {bad}")
        ds = self._frame_dataset(name)
        if column is not None and not (ds.ndim >= 2 and -ds.shape[1] <= column < ds.shape[1]):
            raise ParameterError(f"column: expected an index of the second axis of {name} {ds.shape}, got {column}")
        loaded = self._loaded(name)
        if loaded is not None:
            return loaded[frames] if column is None else loaded[frames, column]
        tail = ds.shape[1:] if column is None else ds.shape[2:]
        if frames.size == 0:
            return np.empty((0,) + tail, dtype=ds.dtype)
        uniq, inv = np.unique(frames, return_inverse=True)
        cut = np.flatnonzero(np.diff(uniq) != 1) + 1
        parts = [ds[int(r[0]):int(r[-1]) + 1] if column is None else ds[int(r[0]):int(r[-1]) + 1, column]
                 for r in np.split(uniq, cut)]
        return np.concatenate(parts)[inv.reshape(-1)]

    def _loaded(self, name: str) -> np.ndarray | None:
        """The per-frame array ``name`` if it is loaded already or can be mapped (which reads nothing), else None."""
        loaded = self.__dict__.get(name)
        if loaded is None and self.map_frames and not self._shard_files:
            ds = self._h5.get(self.FRAME_ARRAYS[name])
            if ds is not None and mappable(ds, self._h5):
                loaded = getattr(self, name)
        return loaded

    def frame_mean(self, name: str, *, chunk: int = 16384, stored: bool = True) -> np.ndarray:
        """Mean over frames of a per-frame array, read ``chunk`` frames at a time.

        Returns ndarray [shape=(...)], float64: ``getattr(db, name).mean(axis=0,
        dtype=np.float64)`` bit for bit (numpy sums along the first axis one row
        after another, and so does this, carrying the sum from chunk to chunk).
        Arrays whose mean the writer stored (:data:`schema.MEAN_FIELDS`) read it
        instead, unless ``stored=False``; files written before it existed are read
        through.
        """
        ds = self._frame_dataset(name)
        path = self.FRAME_ARRAYS[name]
        if stored and path in schema.MEAN_FIELDS:
            mean = schema.read_mean(self._h5, path, self.path)
            if mean is not None:
                return mean.copy()
        loaded = self._loaded(name)
        src = ds if loaded is None else loaded
        acc = np.zeros(ds.shape[1:], dtype=np.float64)
        for a in range(0, self.n_frames, max(int(chunk), 1)):
            block = np.asarray(src[a:a + chunk], dtype=np.float64)
            acc = np.add.reduce(np.concatenate([acc[None], block]), axis=0)
        return acc / self.n_frames

    @functools.cached_property
    def pose_features(self) -> np.ndarray:
        """ndarray [shape=(F, Dp)], float32 C-contiguous, metres (body frame)."""
        return self._frames(schema.POSE_FEATURES)

    @functools.cached_property
    def audio_features(self) -> np.ndarray:
        """ndarray [shape=(F, 14)], float32: standardised 13 MFCC + log mean energy."""
        return self._frames(schema.AUDIO_FEATURES)

    @functools.cached_property
    def audio_deltas(self) -> np.ndarray:
        """ndarray [shape=(F, 14)], float32: first derivative of :attr:`audio_features`."""
        return self._frames(schema.AUDIO_DELTAS)

    @functools.cached_property
    def audio_mean(self) -> np.ndarray:
        return self._read(schema.AUDIO_MEAN)

    @functools.cached_property
    def audio_std(self) -> np.ndarray:
        return self._read(schema.AUDIO_STD)

    @functools.cached_property
    def joint_positions(self) -> np.ndarray:
        """ndarray [shape=(F, J, 3)], float32, world metres, y up."""
        return self._frames(schema.JOINT_POSITIONS)

    @functools.cached_property
    def local_rotations(self) -> np.ndarray:
        """ndarray [shape=(F, J, 4)], float32 unit quaternions (w, x, y, z)."""
        return self._frames(schema.LOCAL_ROTATIONS)

    @functools.cached_property
    def root_positions(self) -> np.ndarray:
        """ndarray [shape=(F, 3)], float32, world metres."""
        return self._frames(schema.ROOT_POSITIONS)

    @functools.cached_property
    def frame_recording(self) -> np.ndarray:
        """ndarray [shape=(F,)], int32: recording index of every frame."""
        return self._frames(schema.FRAME_RECORDING)

    # -- tables ---------------------------------------------------------------
    @functools.cached_property
    def recordings(self) -> list[Recording]:
        cols = {k: self._read(f"{schema.RECORDINGS}/{k}") for k in (
            "name", "speaker", "motion_path", "audio_path", "transcript_path",
            "start_frame", "n_frames", "duration_s", "source_fps", "mirrored")}
        return [
            Recording(
                index=i, name=cols["name"][i], speaker=cols["speaker"][i],
                start_frame=int(cols["start_frame"][i]), n_frames=int(cols["n_frames"][i]),
                duration_s=float(cols["duration_s"][i]), source_fps=float(cols["source_fps"][i]),
                mirrored=bool(cols["mirrored"][i]), motion_path=cols["motion_path"][i],
                audio_path=cols["audio_path"][i], transcript_path=cols["transcript_path"][i],
            )
            for i in range(len(cols["name"]))
        ]

    def speaker_recordings(self, speaker: str) -> list[Recording]:
        """The recordings of one speaker (mirrored copies included); the error lists the speakers there are."""
        recs = [r for r in self.recordings if r.speaker == speaker]
        if not recs:
            raise ParameterError(f"speaker: no recording of speaker {speaker!r} in {self.path}; speakers: "
                                 f"{', '.join(sorted({r.speaker for r in self.recordings}))}")
        return recs

    def recording(self, name_or_index) -> Recording:
        """Look a recording up by name or index; the error lists the names there are."""
        recs = self.recordings
        if isinstance(name_or_index, (int, np.integer)):
            if not 0 <= int(name_or_index) < len(recs):
                raise ParameterError(f"recording: expected an index in [0, {len(recs)}), got {name_or_index}")
            return recs[int(name_or_index)]
        for r in recs:
            if r.name == name_or_index:
                return r
        raise ParameterError(
            f"recording: no recording named {name_or_index!r} in {self.path}; "
            f"recordings: {', '.join(r.name for r in recs)}"
        )

    @functools.cached_property
    def chunks(self) -> Segments:
        """Fixed-length chunks (default 64 frames), the paper's matching sequences."""
        return Segments(self._read(schema.CHUNK_START), self._read(schema.CHUNK_LENGTH), self._read(schema.CHUNK_RECORDING))

    @property
    def segments(self) -> Segments:
        """The default search segments: :attr:`chunks`."""
        return self.chunks

    @functools.cached_property
    def clips(self) -> Clips:
        """Word-gap clips with rhythm and style signatures."""
        r = self._read
        return Clips(
            start=r(schema.CLIP_START), length=r(schema.CLIP_LENGTH), recording=r(schema.CLIP_RECORDING),
            word_start=r(schema.CLIP_WORD_START), word_end=r(schema.CLIP_WORD_END),
            rhythm_audio=r(schema.CLIP_RHYTHM_AUDIO), rhythm_motion=r(schema.CLIP_RHYTHM_MOTION),
            style=r(schema.CLIP_STYLE),
        )

    @functools.cached_property
    def words(self) -> WordTable:
        r = self._read
        return WordTable(r(schema.WORD_RECORDING), r(schema.WORD_START_S), r(schema.WORD_END_S), r(schema.WORD_TEXT))

    @functools.cached_property
    def joint_names(self) -> list[str]:
        return self._read(schema.SKELETON_NAMES)

    @functools.cached_property
    def skeleton(self):
        """The :class:`gesturedb.motion.Skeleton` of every recording in the database."""
        end_joints = self._read(schema.SKELETON_END_SITE_JOINTS)
        end_offsets = self._read(schema.SKELETON_END_SITE_OFFSETS)
        return Skeleton(
            names=list(self.joint_names),
            parents=self._read(schema.SKELETON_PARENTS),
            offsets=self._read(schema.SKELETON_OFFSETS),
            channel_orders=self._read(schema.SKELETON_CHANNEL_ORDERS),
            end_sites={int(j): np.asarray(o, dtype=np.float64) for j, o in zip(end_joints, end_offsets)},
            length_unit_m=float(self._h5[schema.SKELETON].attrs.get(schema.LENGTH_UNIT_ATTR, 1.0)),
        )

    # -- motion graph (GestureMaster) -----------------------------------------
    @property
    def has_motion_graphs(self) -> bool:
        """Whether the file holds both motion graphs and the style model (``gesturedb graph`` adds them)."""
        return all(p in self._h5 for p in (schema.GRAPH_INDPTR, schema.GRAPH_LOWER_INDPTR, schema.STYLE_COEF))

    def motion_graph(self, part: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One body part's motion graph as CSR arrays ``(indptr, indices, cost)``.

        Parameters
        ----------
        part : {"upper", "lower"}
            The upper body (rhythm, style and transitions) or the root and legs (transitions).

        Returns
        -------
        indptr : ndarray [shape=(K + 1,)], int64
        indices : ndarray [shape=(G,)], int64, target clip of each edge
        cost : ndarray [shape=(G,)], float64, transition cost
        """
        groups = {"upper": schema.GRAPH_UPPER, "lower": schema.GRAPH_LOWER}
        if part not in groups:
            raise ParameterError(f"part: expected 'upper' or 'lower', got {part!r}")
        return tuple(self._read(p) for p in schema.GRAPHS[groups[part]])

    @functools.cached_property
    def style_model(self) -> dict[str, np.ndarray]:
        """The clip-style predictor: ``coef`` (P, S), ``intercept`` (S,), ``x_mean`` and ``x_std`` (P,), float64."""
        return {k: self._read(p) for k, p in schema.STYLE_MODEL_FIELDS.items()}

    # -- controls and masks ---------------------------------------------------
    @functools.cached_property
    def controls(self) -> dict[str, np.ndarray]:
        """Per-frame control features: name -> ndarray [shape=(F,)], float32 (units in :attr:`control_units`)."""
        g = self._h5.get(schema.CONTROLS_GROUP)
        return {} if g is None else {k: np.asarray(g[k][()], dtype=np.float32) for k in sorted(g)}

    @functools.cached_property
    def control_datasets(self) -> dict:
        """The control features as h5py datasets, read when used: name -> Dataset [shape=(F,)], float32.

        What a synthesis hands the mask compiler, which reads only the features an
        expression names (4 bytes per frame each) instead of all of :attr:`controls`.
        """
        g = self._h5.get(schema.CONTROLS_GROUP)
        return {} if g is None else {k: g[k] for k in sorted(g)}

    @functools.cached_property
    def mask_datasets(self) -> dict:
        """Saved masks as h5py datasets, read when an expression uses them (see :attr:`masks`)."""
        g = self._masks_group()
        return {} if g is None else {k: g[k] for k in sorted(g)}

    def control_attrs(self, name: str) -> dict:
        """The stored attributes (``unit``, ``doc``) of the control feature ``name``."""
        return dict(self._h5[f"{schema.CONTROLS_GROUP}/{name}"].attrs)

    def mask_attrs(self, name: str) -> dict:
        """The stored attributes (``definition``, ``thresholds`` as JSON) of the saved mask ``name``."""
        return dict(self._masks_group()[name].attrs)

    @functools.cached_property
    def control_units(self) -> dict[str, str]:
        g = self._h5.get(schema.CONTROLS_GROUP)
        return {} if g is None else {k: str(g[k].attrs.get("unit", "")) for k in sorted(g)}

    @functools.cached_property
    def masks(self) -> dict[str, np.ndarray]:
        """Saved masks: name -> packed uint64 bitset over frames."""
        g = self._masks_group()
        return {} if g is None else {k: np.asarray(g[k][()], dtype=np.uint64) for k in sorted(g)}

    def _masks_group(self):
        import h5py

        g = self._h5.get(schema.MASKS_GROUP)
        for k in ([] if g is None else g):
            if not isinstance(g[k], h5py.Dataset):
                raise SchemaError(self.path, f"{schema.MASKS_GROUP}/{k}: expected a saved mask (a dataset), got a "
                                  f"group (a mask name with '/'?); repair with `gesturedb masks DB remove {k}`")
        return g

    @functools.cached_property
    def mask_definitions(self) -> dict[str, str]:
        g = self._masks_group()
        return {} if g is None else {k: str(g[k].attrs.get("definition", "")) for k in sorted(g)}

    # -- motion out -----------------------------------------------------------
    def frame_range(self, recording, start_s: float | None = None, end_s: float | None = None) -> tuple[int, int]:
        """Global frame range `[a, b)` of a stretch of a recording (times in seconds)."""
        rec = self.recording(recording)
        a = 0 if start_s is None else int(round(start_s * self.fps))
        b = rec.n_frames if end_s is None else int(round(end_s * self.fps))
        if not (0 <= a < b <= rec.n_frames):
            raise ParameterError(
                f"time range: expected 0 <= start < end <= {rec.duration_s:.3f} s for recording {rec.name!r}, "
                f"got start={start_s}, end={end_s}"
            )
        return rec.start_frame + a, rec.start_frame + b

    def motion(self, recording, start_s: float | None = None, end_s: float | None = None):
        """A stretch of a recording as a :class:`gesturedb.motion.Motion` (for BVH export)."""
        a, b = self.frame_range(recording, start_s, end_s)
        return self.motion_from_frames(np.arange(a, b))

    def motion_from_frames(self, frames: np.ndarray):
        """A :class:`Motion` made of arbitrary database frames (e.g. a synthesis result)."""
        frames = np.asarray(frames, dtype=np.int64)
        return Motion(
            skeleton=self.skeleton,
            fps=self.fps,
            rotations=np.asarray(self.local_rotations[frames], dtype=np.float64),
            root_positions=np.asarray(self.root_positions[frames], dtype=np.float64),
        )


def mappable(ds, h5=None) -> bool:
    """Whether the h5py dataset ``ds`` can be memory-mapped by :meth:`Database._mapped`.

    Only a dataset stored as one run of bytes of its own file, exactly as numpy lays the array
    out: contiguous layout with its storage allocated (``get_offset()`` is not None), no chunks,
    no filters (compression, shuffle, checksums), not virtual (an index file's per-frame arrays
    over its shards) and not external, a plain native little-endian number dtype, in a file
    opened with HDF5's default POSIX driver (whose descriptor is mapped). Anything else is read.
    """
    h5 = ds.file if h5 is None else h5
    dt = ds.dtype
    if (sys.byteorder != "little" or h5.driver != "sec2" or ds.is_virtual or ds.chunks is not None
            or ds.external or dt.kind not in "biuf" or not dt.isnative or dt.fields is not None
            or dt.subdtype is not None or ds.id.get_create_plist().get_nfilters() != 0 or ds.size == 0):
        return False
    return ds.id.get_offset() is not None and ds.id.get_storage_size() == ds.nbytes


def _open_same_file(fd: int, path: str) -> int | None:
    """A new read-only descriptor of the file open as ``fd``, or None if there is no way to one.

    Not a duplicate of ``fd``: HDF5 locks its files with ``flock``, which a duplicate shares,
    so a map made from one would hold HDF5's read lock for as long as an array lives, after
    the database is closed. Opened by ``path`` when that is still the same file (device and
    inode), else through ``/proc/self/fd`` (the file was renamed over or removed since).
    """
    want = os.fstat(fd)
    for name in (path, f"/proc/self/fd/{fd}"):
        try:
            new = os.open(name, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            continue
        st = os.fstat(new)
        if (st.st_dev, st.st_ino) == (want.st_dev, want.st_ino):
            return new
        os.close(new)
    return None


def _inode(path: str):
    """(device, inode) of ``path``, or None if there is no such file (an index replaced by a rename changes it)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _allow_open_files(n: int) -> None:
    """Raise the soft limit on open files if an index's ``n`` shard files would not fit under it."""
    try:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        need = n + 256
        if soft != resource.RLIM_INFINITY and soft < need:
            resource.setrlimit(resource.RLIMIT_NOFILE, (need if hard == resource.RLIM_INFINITY else min(need, hard), hard))
    except (ImportError, ValueError, OSError):
        pass  # opening a shard then fails with a one-line error naming it
