"""The gesture-database file format: every HDF5 dataset, dtype, shape, unit and attribute.

This module is the only place that knows dataset paths: every other module names a
dataset by one of the constants below (``schema.POSE_FEATURES``), and modules outside
:mod:`gesturedb.db` ask the :class:`~gesturedb.db.database.Database` instead (tested in
``tests/test_architecture.py``). Writers go through :func:`write` and :class:`RowWriter`,
which check dtype and shape against the declaration and store through
:mod:`gesturedb.db.store`; readers go through :func:`read` and :func:`check_version`.

Symbolic dimensions used in the shapes below:

====  =====================================================================
F     database frames (all recordings, concatenated, at the database fps)
J     skeleton joints
R     recordings (a mirrored copy counts as its own recording)
C     fixed-length chunks (default 64 frames; the paper's "sequences")
K     word-gap clips (GestureMaster Sec. 3.1)
W     words (all recordings)
E     skeleton End Sites
Dp    pose-feature size (8 joints x 3 x pose window; 96 by default)
Da    audio-feature size (13 MFCC + log mean energy = 14)
B     bitset words over frames, ceil(F / 64)
S     style-signature size (3: speed m/s, radius m, height m)
X     control features
K1    K + 1 (CSR row pointer of the motion graph)
G     upper-body motion-graph edges
GL    lower-body motion-graph edges
P     style-predictor inputs (2 Da + 1)
====  =====================================================================

Bump :data:`SCHEMA_VERSION` whenever a dataset changes meaning, dtype or shape.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from gesturedb.db import store
from gesturedb.errors import ParameterError, SchemaError

#: 2: adds graph/ and style_model/ (GestureMaster motion graph)
#: 3: graph/ is the upper-body graph (it was over the whole body), graph_lower/ the lower-body one (Sec. 4.1)
#: 4: frames/pose_features stack frames centred on each frame instead of its past only, config pose_stride apart
#: 5: frames/pose_features carry the ankles (the stance) after the 8 feature joints, where the rig has legs
#: `gesturedb upgrade DB.h5` (:mod:`gesturedb.db.upgrade`) brings any of them to SCHEMA_VERSION
SCHEMA_VERSION = 5
#: versions `gesturedb upgrade` brings to SCHEMA_VERSION, and what each lacks
UPGRADABLE_VERSIONS = {
    1: "no motion graph, pose features of the past only",
    2: "one motion graph over the whole body, pose features of the past only",
    3: "pose features of the past only",
    4: "pose features without the stance (the ankles)",
}

#: HDF5 variable-length UTF-8 strings
STR = "str"


@dataclass(frozen=True)
class Field:
    """One dataset of the file: its path, dtype, symbolic shape, unit and meaning."""

    path: str
    dtype: str
    shape: tuple[str | int, ...]
    unit: str
    doc: str


# --------------------------------------------------------------------------
# dataset paths: every reader and writer names a dataset by one of these
# --------------------------------------------------------------------------
#: groups
RECORDINGS = "recordings"
FRAMES = "frames"
AUDIO = "audio"
SKELETON = "skeleton"
CHUNKS = "chunks"
CLIPS = "clips"
GRAPH_UPPER = "graph"
GRAPH_LOWER = "graph_lower"
STYLE_MODEL = "style_model"
WORDS = "words"

RECORDING_NAME = f"{RECORDINGS}/name"
RECORDING_SPEAKER = f"{RECORDINGS}/speaker"
RECORDING_MOTION_PATH = f"{RECORDINGS}/motion_path"
RECORDING_AUDIO_PATH = f"{RECORDINGS}/audio_path"
RECORDING_TRANSCRIPT_PATH = f"{RECORDINGS}/transcript_path"
RECORDING_START_FRAME = f"{RECORDINGS}/start_frame"
RECORDING_N_FRAMES = f"{RECORDINGS}/n_frames"
RECORDING_DURATION_S = f"{RECORDINGS}/duration_s"
RECORDING_SOURCE_FPS = f"{RECORDINGS}/source_fps"
RECORDING_MIRRORED = f"{RECORDINGS}/mirrored"

POSE_FEATURES = f"{FRAMES}/pose_features"
AUDIO_FEATURES = f"{FRAMES}/audio_features"
AUDIO_DELTAS = f"{FRAMES}/audio_deltas"
JOINT_POSITIONS = f"{FRAMES}/joint_positions"
LOCAL_ROTATIONS = f"{FRAMES}/local_rotations"
ROOT_POSITIONS = f"{FRAMES}/root_positions"
FRAME_RECORDING = f"{FRAMES}/recording"

AUDIO_MEAN = f"{AUDIO}/mean"
AUDIO_STD = f"{AUDIO}/std"

SKELETON_NAMES = f"{SKELETON}/names"
SKELETON_PARENTS = f"{SKELETON}/parents"
SKELETON_OFFSETS = f"{SKELETON}/offsets"
SKELETON_CHANNEL_ORDERS = f"{SKELETON}/channel_orders"
SKELETON_END_SITE_JOINTS = f"{SKELETON}/end_site_joints"
SKELETON_END_SITE_OFFSETS = f"{SKELETON}/end_site_offsets"

CHUNK_START = f"{CHUNKS}/start"
CHUNK_LENGTH = f"{CHUNKS}/length"
CHUNK_RECORDING = f"{CHUNKS}/recording"

CLIP_START = f"{CLIPS}/start"
CLIP_LENGTH = f"{CLIPS}/length"
CLIP_RECORDING = f"{CLIPS}/recording"
CLIP_WORD_START = f"{CLIPS}/word_start"
CLIP_WORD_END = f"{CLIPS}/word_end"
CLIP_RHYTHM_AUDIO = f"{CLIPS}/rhythm_audio"
CLIP_RHYTHM_MOTION = f"{CLIPS}/rhythm_motion"
CLIP_STYLE = f"{CLIPS}/style"

GRAPH_INDPTR = f"{GRAPH_UPPER}/indptr"
GRAPH_INDICES = f"{GRAPH_UPPER}/indices"
GRAPH_COST = f"{GRAPH_UPPER}/cost"

GRAPH_LOWER_INDPTR = f"{GRAPH_LOWER}/indptr"
GRAPH_LOWER_INDICES = f"{GRAPH_LOWER}/indices"
GRAPH_LOWER_COST = f"{GRAPH_LOWER}/cost"

STYLE_COEF = f"{STYLE_MODEL}/coef"
STYLE_INTERCEPT = f"{STYLE_MODEL}/intercept"
STYLE_X_MEAN = f"{STYLE_MODEL}/x_mean"
STYLE_X_STD = f"{STYLE_MODEL}/x_std"

WORD_RECORDING = f"{WORDS}/recording"
WORD_START_S = f"{WORDS}/start_s"
WORD_END_S = f"{WORDS}/end_s"
WORD_TEXT = f"{WORDS}/text"

#: the two motion graphs: group -> (indptr, indices, cost)
GRAPHS = {GRAPH_UPPER: (GRAPH_INDPTR, GRAPH_INDICES, GRAPH_COST),
          GRAPH_LOWER: (GRAPH_LOWER_INDPTR, GRAPH_LOWER_INDICES, GRAPH_LOWER_COST)}
#: the style model: key of :func:`gesturedb.db.graph.fit_style_model`'s result -> dataset
STYLE_MODEL_FIELDS = {"coef": STYLE_COEF, "intercept": STYLE_INTERCEPT, "x_mean": STYLE_X_MEAN, "x_std": STYLE_X_STD}
#: attribute of the skeleton group: metres per length unit of the source files
LENGTH_UNIT_ATTR = "length_unit_m"


FIELDS: tuple[Field, ...] = (
    # --- recordings table --------------------------------------------------
    Field(RECORDING_NAME, STR, ("R",), "", "recording name (file stem; mirrored copies end in '~mirror')"),
    Field(RECORDING_SPEAKER, STR, ("R",), "", "speaker name"),
    Field(RECORDING_MOTION_PATH, STR, ("R",), "", "source motion file (BVH or SMPL-X npz), as given"),
    Field(RECORDING_AUDIO_PATH, STR, ("R",), "", "source speech WAV"),
    Field(RECORDING_TRANSCRIPT_PATH, STR, ("R",), "", "source transcript ('' if none)"),
    Field(RECORDING_START_FRAME, "int64", ("R",), "frame", "first database frame of the recording"),
    Field(RECORDING_N_FRAMES, "int64", ("R",), "frame", "number of database frames"),
    Field(RECORDING_DURATION_S, "float64", ("R",), "s", "n_frames / fps"),
    Field(RECORDING_SOURCE_FPS, "float64", ("R",), "Hz", "frame rate of the source motion"),
    Field(RECORDING_MIRRORED, "bool", ("R",), "", "left/right mirrored copy of another recording"),
    # --- per-frame arrays --------------------------------------------------
    Field(POSE_FEATURES, "float32", ("F", "Dp"), "m",
          "feature joints, then the ankles where the rig has legs, in the body frame of the current frame, "
          "stacked over a window centred on it; attr `mean`: float64 (Dp,), its mean over frames"),
    Field(AUDIO_FEATURES, "float32", ("F", "Da"), "1",
          "13 MFCC + log mean energy per frame, standardised with audio/mean and audio/std"),
    Field(AUDIO_DELTAS, "float32", ("F", "Da"), "1/frame",
          "first time derivative of the standardised audio features (refiner input)"),
    Field(JOINT_POSITIONS, "float32", ("F", "J", 3), "m", "world joint positions, y up"),
    Field(LOCAL_ROTATIONS, "float32", ("F", "J", 4), "1",
          "local joint rotations as unit quaternions w, x, y, z"),
    Field(ROOT_POSITIONS, "float32", ("F", 3), "m", "world position of the root joint"),
    Field(FRAME_RECORDING, "int32", ("F",), "", "index into the recordings table"),
    # --- audio normalisation ----------------------------------------------
    Field(AUDIO_MEAN, "float64", ("Da",), "1", "per-dimension mean of the raw audio features"),
    Field(AUDIO_STD, "float64", ("Da",), "1", "per-dimension standard deviation of the raw audio features"),
    # --- skeleton ----------------------------------------------------------
    Field(SKELETON_NAMES, STR, ("J",), "", "joint names"),
    Field(SKELETON_PARENTS, "int64", ("J",), "", "parent joint index, -1 for the root"),
    Field(SKELETON_OFFSETS, "float64", ("J", 3), "m", "rest offset of each joint from its parent"),
    Field(SKELETON_CHANNEL_ORDERS, STR, ("J",), "", "Euler order of the rotation channels for BVH export"),
    Field(SKELETON_END_SITE_JOINTS, "int64", ("E",), "", "joints that carry an End Site"),
    Field(SKELETON_END_SITE_OFFSETS, "float64", ("E", 3), "m", "End Site offsets"),
    # --- fixed-length chunks (Habibie et al. 2022: T_match = 64) ----------
    Field(CHUNK_START, "int64", ("C",), "frame", "first database frame"),
    Field(CHUNK_LENGTH, "int64", ("C",), "frame", "length in frames (the last chunk of a recording may be shorter)"),
    Field(CHUNK_RECORDING, "int32", ("C",), "", "index into the recordings table"),
    # --- word-gap clips (GestureMaster) ------------------------------------
    Field(CLIP_START, "int64", ("K",), "frame", "first database frame"),
    Field(CLIP_LENGTH, "int64", ("K",), "frame", "length in frames"),
    Field(CLIP_RECORDING, "int32", ("K",), "", "index into the recordings table"),
    Field(CLIP_WORD_START, "int64", ("K",), "", "first word of the clip (index into words/)"),
    Field(CLIP_WORD_END, "int64", ("K",), "", "one past the last word of the clip"),
    Field(CLIP_RHYTHM_AUDIO, "uint32", ("K",), "", "32-bit rhythm signature of word onsets (bin 0 = LSB)"),
    Field(CLIP_RHYTHM_MOTION, "uint32", ("K",), "", "32-bit rhythm signature of hand-speed minima (bin 0 = LSB)"),
    Field(CLIP_STYLE, "float32", ("K", "S"), "m/s, m, m", "mean hand speed, radius and height"),
    # --- motion graph over the clips (GestureMaster Sec. 4.1; gesturedb/db/graph.py) ----------
    Field(GRAPH_INDPTR, "int64", ("K1",), "", "upper-body graph: CSR row pointer over the source clip; attrs body, l1, l2, delta_T, min_out, max_out, transition_frames"),
    Field(GRAPH_INDICES, "int64", ("G",), "", "upper-body graph: target clip of each edge, strictly increasing within a row, no self-edges"),
    Field(GRAPH_COST, "float64", ("G",), "1", "upper-body graph: transition cost T = l1 * T_p (m^2) + l2 * T_r over the joints above the pelvis, in the pelvis frame"),
    Field(GRAPH_LOWER_INDPTR, "int64", ("K1",), "", "lower-body graph (root and legs): CSR row pointer, attrs as graph/"),
    Field(GRAPH_LOWER_INDICES, "int64", ("GL",), "", "lower-body graph: target clip of each edge, strictly increasing within a row, no self-edges"),
    Field(GRAPH_LOWER_COST, "float64", ("GL",), "1", "lower-body graph: transition cost over the legs (heading frame) and the pelvis tilt"),
    Field(STYLE_COEF, "float64", ("P", "S"), "", "ridge weights: standardised clip audio inputs -> style"),
    Field(STYLE_INTERCEPT, "float64", ("S",), "m/s, m, m", "style of the mean input"),
    Field(STYLE_X_MEAN, "float64", ("P",), "", "input mean (audio mean, audio std, words/frame)"),
    Field(STYLE_X_STD, "float64", ("P",), "", "input standard deviation; attrs heldout_rmse, mean_rmse"),
    # --- words -------------------------------------------------------------
    Field(WORD_RECORDING, "int32", ("W",), "", "index into the recordings table"),
    Field(WORD_START_S, "float64", ("W",), "s", "word start, relative to the recording"),
    Field(WORD_END_S, "float64", ("W",), "s", "word end, relative to the recording"),
    Field(WORD_TEXT, STR, ("W",), "", "the word, lower case, no punctuation"),
)

FIELDS_BY_PATH: dict[str, Field] = {f.path: f for f in FIELDS}

#: Groups whose members are named at run time (one dataset per control feature / mask).
CONTROLS_GROUP = "controls"  # controls/<name>: float32 (F,), attrs unit, doc
MASKS_GROUP = "masks"  # masks/<name>: uint64 (B,), attrs definition, thresholds (JSON)
SUBDB_GROUP = "subdatabases"  # subdatabases/<name>/{start,length,recording} + attrs definition

#: Dataset attribute: the float64 mean over frames of a per-frame array, numpy's
#: ``arr.mean(axis=0, dtype=np.float64)`` bit for bit, written with the array so that
#: ``synth --init mean`` reads Dp numbers instead of the whole array (21 GB at 1,000 hours).
#: Files written before it existed lack it; readers then compute it (Database.frame_mean).
MEAN_ATTR = "mean"
#: the per-frame arrays that carry MEAN_ATTR
MEAN_FIELDS = (POSE_FEATURES,)

#: A database split over several files (``gesturedb shard``): the per-frame arrays below live in shard
#: files of whole recordings; the index file holds everything else and these arrays as HDF5 virtual
#: datasets over the shards, so the index reads exactly like the single file (gesturedb/db/shardfiles.py).
SHARDED_FIELDS = (POSE_FEATURES, AUDIO_FEATURES, AUDIO_DELTAS, JOINT_POSITIONS, LOCAL_ROTATIONS, ROOT_POSITIONS,
                  FRAME_RECORDING)
#: The per-frame arrays a reader memory-maps (gesturedb/db/database.py) when they are stored contiguous:
#: builds and edits store them so (:func:`gesturedb.db.storage.compact_copy`), a storage layout, not a
#: schema change: files with these chunked (written before) are read as they were.
CONTIGUOUS_FIELDS = SHARDED_FIELDS
#: root attribute of an index file: JSON list of {"file": name beside the index, "frames": [f0, f1], "token": str}
SHARDS_ATTR = "shards"
#: root attribute of a shard file: JSON {"token", "part" (1-based), "parts", "frames": [f0, f1], "index": name}
SHARD_OF_ATTR = "shard_of"

#: the audio sample rate (Hz) of the build configuration's default, and of a database whose
#: ``config`` names none (:attr:`gesturedb.db.database.Database.sample_rate`)
DEFAULT_SAMPLE_RATE = 16000

#: Root attributes (name -> meaning). `config` and `feature_joints` are JSON.
ROOT_ATTRS = {
    "schema_version": "int: SCHEMA_VERSION of the writer",
    "gesturedb_version": "str: package version that wrote the file",
    "fps": "float: database frame rate (Hz)",
    "n_frames": "int: F",
    "config": "JSON: the complete build configuration",
    "feature_joints": "JSON: role -> joint name used for the features",
    "motion_timescale_s": "float: the arms' motion timescale (s), whence the pose stride (features.pose)",
    SHARDS_ATTR: "JSON (index files only): the shard files holding the per-frame arrays, in frame order",
    SHARD_OF_ATTR: "JSON (shard files only): which part of which index the file is",
    f"{SKELETON}/{LENGTH_UNIT_ATTR}": "float (attribute of the skeleton group): metres per length unit of the source files",
}


# --------------------------------------------------------------------------
# writing and reading
# --------------------------------------------------------------------------

def _h5py():
    import h5py  # imported lazily so `import gesturedb` stays light

    return h5py


def _np_dtype(dtype: str):
    if dtype == STR:
        return _h5py().string_dtype("utf-8")
    return np.dtype(dtype)


def _check_shape(field: Field, arr: np.ndarray, dims: dict[str, int]) -> None:
    if arr.ndim != len(field.shape):
        raise SchemaError(
            "<writing>", f"{field.path}: expected {len(field.shape)} dimensions {field.shape}, got shape {arr.shape}"
        )
    for axis, (want, got) in enumerate(zip(field.shape, arr.shape)):
        if isinstance(want, int):
            if got != want:
                raise SchemaError("<writing>", f"{field.path}: axis {axis} expected {want}, got {got}")
        else:
            seen = dims.setdefault(want, got)
            if seen != got:
                raise SchemaError(
                    "<writing>",
                    f"{field.path}: dimension {want} expected {seen} (from another dataset), got {got}",
                )


def _checked(field: Field, data: Any, row0: int = 0) -> np.ndarray:
    """``data`` as the field's dtype (lossless kinds only) and finite, or a SchemaError naming the field
    and the first bad index (rows counted from ``row0``)."""
    if field.dtype == STR:
        return np.asarray([str(s) for s in data], dtype=object)
    arr = np.asarray(data)
    want = np.dtype(field.dtype)
    if arr.size and arr.dtype.kind != want.kind and not (arr.dtype.kind in "iub" and want.kind in "iub"):
        raise SchemaError("<writing>", f"{field.path}: expected {want}, got {arr.dtype}")
    arr = arr.astype(want, copy=False)
    if want.kind == "f" and arr.size and not np.isfinite(arr).all():
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])
        at = (idx[0] + row0,) + idx[1:]
        raise SchemaError("<writing>", f"{field.path}: expected finite values, got {arr[idx]} at index {at}; "
                                       "refusing to write a database with non-finite data")
    return arr


def add_rows(total: np.ndarray | None, rows: Any) -> np.ndarray:
    """``total + rows.sum(axis=0)`` in float64, adding row after row as numpy's axis-0 sum of the
    whole array does (so a sum over blocks of rows has the whole array's bits; ``total`` None:
    nothing yet)."""
    rows = np.asarray(rows, dtype=np.float64)
    return np.add.reduce(rows if total is None else np.concatenate([total[None], rows]), axis=0)


class RowWriter:
    """One declared per-row dataset that grows a block of rows at a time.

    The build appends each recording's rows as it arrives instead of holding every recording
    and concatenating them (at 100 hours, tens of gigabytes on the client). The same checks as
    :func:`write` (dtype, finite; the trailing dimensions now, the rows against ``dims`` at
    :meth:`close`) and the same attributes; :data:`MEAN_ATTR` is accumulated row after row in
    float64, which is what numpy's ``mean(axis=0, dtype=float64)`` of the whole array does, so
    its bits are the same (tested). Chunked: ``chunk_rows`` rows a chunk, at most about 4 MB (a
    chunk is stored whole, so a small file wants chunks no longer than its first block).
    """

    CHUNK_BYTES = 1 << 22

    def __init__(self, h5, path: str, row_shape: tuple, chunk_rows: int | None = None):
        self.field = FIELDS_BY_PATH[path]
        row_shape = tuple(row_shape)
        _check_shape(self.field, np.broadcast_to(np.zeros((), np.uint8), (0,) + row_shape), {})
        dtype = _np_dtype(self.field.dtype)
        row_bytes = max(1, int(np.prod(row_shape, dtype=np.int64)) * np.dtype(dtype).itemsize)
        n = self.CHUNK_BYTES // row_bytes if chunk_rows is None else min(int(chunk_rows), self.CHUNK_BYTES // row_bytes)
        self.h5, self.path = h5, path
        self.ds = store.create(h5, path, shape=(0,) + row_shape, dtype=dtype, chunk_rows=n,
                               attrs={"unit": self.field.unit, "doc": self.field.doc})
        self.n = 0
        self.sum = None

    def write(self, data: Any) -> None:
        """The next rows (after those written so far)."""
        arr = _checked(self.field, data, self.n)
        if arr.shape[1:] != self.ds.shape[1:]:
            raise SchemaError("<writing>", f"{self.field.path}: expected rows of shape {self.ds.shape[1:]}, "
                                           f"got {arr.shape} at row {self.n}")
        if arr.shape[0] == 0:
            return
        store.append(self.ds, arr)
        self.n += arr.shape[0]
        if self.field.path in MEAN_FIELDS:
            self.sum = add_rows(self.sum, arr)

    def close(self, dims: dict[str, int]) -> None:
        """After the last rows: their number checked against (and recorded in) ``dims``."""
        _check_shape(self.field, np.broadcast_to(np.zeros((), np.uint8), self.ds.shape), dims)
        if self.sum is not None:
            store.set_attrs(self.h5, self.path, {MEAN_ATTR: self.sum / self.n})


def write(h5, path: str, data: Any, dims: dict[str, int], *, attrs: Mapping[str, Any] | None = None) -> None:
    """Write one declared dataset, checking its dtype and shape.

    Parameters
    ----------
    h5 : h5py.File
    path : str
        A path declared in :data:`FIELDS`.
    data : array-like
        Converted to the declared dtype only when that is lossless for the kind
        (ints to ints, floats to floats); anything else is a programming error.
    dims : dict
        Symbolic dimension sizes seen so far; filled in and checked across datasets.
    """
    field = FIELDS_BY_PATH[path]
    arr = _checked(field, data)
    _check_shape(field, arr, dims)
    extra = {MEAN_ATTR: arr.mean(axis=0, dtype=np.float64)} if path in MEAN_FIELDS and arr.shape[0] > 0 else {}
    store.create(h5, path, arr, dtype=_np_dtype(field.dtype),
                 attrs={"unit": field.unit, "doc": field.doc, **extra, **(attrs or {})})


def read(h5, path: str) -> np.ndarray:
    """Read one declared dataset as a numpy array (strings as a list of str)."""
    field = FIELDS_BY_PATH[path]
    if path not in h5:
        raise SchemaError(h5.filename, f"missing dataset {path!r} ({field.doc})")
    ds = h5[path]
    if field.dtype == STR:
        return [s.decode("utf-8") if isinstance(s, bytes) else str(s) for s in ds.asstr()[()]]
    arr = ds[()]
    if arr.dtype != np.dtype(field.dtype):
        raise SchemaError(h5.filename, f"{path}: expected dtype {field.dtype}, got {arr.dtype}")
    return arr


def check_version(h5, filename: str | os.PathLike | None = None, *, upgradable: bool = False) -> int:
    """Raise :class:`SchemaError` unless the file was written with :data:`SCHEMA_VERSION`.

    ``upgradable=True`` also accepts :data:`UPGRADABLE_VERSIONS`, for
    :func:`gesturedb.db.upgrade.upgrade`.
    """
    name = os.fspath(filename) if filename is not None else h5.filename
    if SHARD_OF_ATTR in h5.attrs:
        of = _json_or(h5, SHARD_OF_ATTR, {})
        of = of if isinstance(of, dict) else {}
        raise SchemaError(name, f"{SHARD_OF_ATTR}: this is part {of.get('part', '?')} of {of.get('parts', '?')} of a "
                                f"sharded database, not a database; open its index file {of.get('index', '?')!r}")
    if "schema_version" not in h5.attrs:
        raise SchemaError(name, "attribute 'schema_version' is missing: not a gesturedb database")
    raw = h5.attrs["schema_version"]
    try:
        got = int(raw)
        if got != float(raw):
            raise ValueError
    except (TypeError, ValueError):
        raise SchemaError(name, f"schema_version: expected the integer {SCHEMA_VERSION}, got {raw!r}") from None
    if upgradable and got in UPGRADABLE_VERSIONS:
        return got
    if got in UPGRADABLE_VERSIONS:
        raise SchemaError(
            name,
            f"schema_version: expected {SCHEMA_VERSION}, got {got} ({UPGRADABLE_VERSIONS[got]}); run "
            f"`gesturedb upgrade {name}` to bring it up to date from what it keeps, or rebuild the database",
        )
    if got != SCHEMA_VERSION:
        raise SchemaError(
            name,
            f"schema_version: expected {SCHEMA_VERSION}, got {got} "
            f"(written by gesturedb {h5.attrs.get('gesturedb_version', '?')}); rebuild the database "
            f"with this version or open it with the version that wrote it",
        )
    return got


#: groups every database has (the motion graph, the style model etc. are optional: exported keyword
#: databases, ``--no-graph`` builds and version-1 files lack them)
_CORE_GROUPS = ("recordings", "frames", "audio", "skeleton", "chunks", "clips", "words")

#: rows of each per-frame array read by :func:`check_file` (spread over the file): the check stays cheap
CHECK_SAMPLE_ROWS = 2000


def read_mean(h5, path: str, filename: str | os.PathLike | None = None) -> np.ndarray | None:
    """The :data:`MEAN_ATTR` of the per-frame dataset ``path``, checked; None when the file has none.

    Returns ndarray [shape=(D...,)], float64 (the dataset's shape without its frame axis).
    Raises :class:`SchemaError` naming the file and the attribute when it has another
    dtype or shape, or a non-finite value.
    """
    ds = h5[path]
    if MEAN_ATTR not in ds.attrs:
        return None
    name = os.fspath(filename) if filename is not None else h5.filename
    got = np.asarray(ds.attrs[MEAN_ATTR])
    if got.dtype != np.float64 or got.shape != ds.shape[1:]:
        raise SchemaError(name, f"{path} attribute {MEAN_ATTR!r}: expected float64 of shape {ds.shape[1:]}, "
                                f"got {got.dtype} of shape {got.shape}")
    if not np.isfinite(got).all():
        raise SchemaError(name, f"{path} attribute {MEAN_ATTR!r}: expected finite values, "
                                f"got {got[~np.isfinite(got)][0]}")
    return got


def check_file(h5, filename: str | os.PathLike | None = None, *, sample=None) -> None:
    """Cheap invariants of an opened database; :class:`SchemaError` naming the dataset if one fails.

    Checked: root attributes (``fps`` in 1-1000, ``n_frames``, ``config`` and
    ``feature_joints`` JSON), every declared dataset present with its dtype kind
    and shape, index ranges (recordings, chunks, clips, words, skeleton parents),
    finite audio statistics, and finite values / non-zero quaternions in up to
    :data:`CHECK_SAMPLE_ROWS` rows of each per-frame array. ``sample(path, rows)``, optional, reads
    those rows of ``path`` instead of h5py's point selection (most of a 616k-frame database's
    open): ``Database`` reads them from its memory maps.
    """
    h5py = _h5py()
    name = os.fspath(filename) if filename is not None else h5.filename

    def fail(problem):
        raise SchemaError(name, problem)

    check_version(h5, name)
    if SHARDS_ATTR in h5.attrs:
        check_shards(h5, name)
    try:
        fps = float(h5.attrs.get("fps"))
    except (TypeError, ValueError):
        fail(f"fps: expected a frame rate in Hz, got {h5.attrs.get('fps')!r}")
    if not (np.isfinite(fps) and 1.0 <= fps <= 1000.0):
        fail(f"fps: expected a frame rate from 1 to 1000 Hz, got {fps}")
    try:
        n_frames = int(h5.attrs.get("n_frames"))
    except (TypeError, ValueError):
        fail(f"n_frames: expected an integer, got {h5.attrs.get('n_frames')!r}")
    for attr in ("config", "feature_joints"):
        if attr not in h5.attrs:  # optional: Database reads it with a default
            continue
        try:
            value = json.loads(h5.attrs[attr])
        except (TypeError, ValueError):
            fail(f"{attr}: expected a JSON object, got {str(h5.attrs[attr])[:60]!r}")
        if not isinstance(value, dict):
            fail(f"{attr}: expected a JSON object, got {type(value).__name__}")
    dims: dict[str, int] = {"F": n_frames}
    for f in FIELDS:
        ds = h5.get(f.path)
        if ds is None:
            # a file written by build holds every dataset; a hand-made partial file (tests) meets read()'s check
            # (the motion graph is optional: exported keyword databases and version-1 files have none)
            if "gesturedb_version" in h5.attrs and f.path.split("/")[0] in _CORE_GROUPS:
                fail(f"{f.path}: dataset missing ({f.doc})")
            continue
        if not isinstance(ds, h5py.Dataset):
            fail(f"{f.path}: expected a dataset, got a group")
        is_str = ds.dtype.kind in "OSU"
        if (f.dtype == STR) != is_str or (not is_str and np.dtype(f.dtype).kind != ds.dtype.kind):
            fail(f"{f.path}: expected dtype {f.dtype}, got {ds.dtype}")
        if len(ds.shape) != len(f.shape):
            fail(f"{f.path}: expected shape {f.shape}, got {ds.shape}")
        for want, got in zip(f.shape, ds.shape):
            if isinstance(want, int) and want != got:
                fail(f"{f.path}: expected shape {f.shape}, got {ds.shape}")
            if isinstance(want, str) and dims.setdefault(want, got) != got:
                fail(f"{f.path}: dimension {want} expected {dims[want]} (from the other datasets), got {got}")
    R, F, J, W = (dims.get(k, 0) for k in "RFJW")

    def have(*paths):
        return all(p in h5 for p in paths)

    if have("recordings/name") and (R < 1 or F < 1):
        fail(f"recordings/name: expected at least one recording and frame, got {R} recordings, {F} frames")

    def ints(path):
        return np.asarray(h5[path][()])

    start, n = (ints(p) if have(p) else np.zeros(0, np.int64) for p in ("recordings/start_frame", "recordings/n_frames"))
    if start.shape != n.shape:
        fail(f"recordings/start_frame: expected {n.shape[0]} entries like recordings/n_frames, got {start.shape[0]}")
    if (n < 1).any() or (start < 0).any() or (start + n > F).any():
        i = int(np.flatnonzero((n < 1) | (start < 0) | (start + n > F))[0])
        fail(f"recordings/start_frame, n_frames: recording {i} spans frames {start[i]}..{start[i] + n[i]}, "
             f"expected within 0..{F}")
    parents = ints("skeleton/parents") if have("skeleton/parents") else np.full(J, -1)[:1]
    J = len(parents)
    bad = np.flatnonzero(~((parents >= -1) & (parents < np.arange(J))) | ((np.arange(J) == 0) != (parents == -1)))
    if bad.size:
        fail(f"skeleton/parents: joint {int(bad[0])} has parent {int(parents[bad[0]])}, expected -1 for joint 0 "
             f"and a smaller index for the others")
    ej = ints("skeleton/end_site_joints") if have("skeleton/end_site_joints") else np.zeros(0, np.int64)
    if ((ej < 0) | (ej >= J)).any():
        fail(f"skeleton/end_site_joints: expected indices in 0..{J - 1}, got {ej[(ej < 0) | (ej >= J)][0]}")
    for group, total in (("chunks", F), ("clips", F)):
        if not have(f"{group}/start", f"{group}/length", f"{group}/recording"):
            continue
        s, ln, rec = ints(f"{group}/start"), ints(f"{group}/length"), ints(f"{group}/recording")
        bad = np.flatnonzero((s < 0) | (ln < 1) | (s + ln > total) | (rec < 0) | (rec >= R))
        if bad.size:
            i = int(bad[0])
            fail(f"{group}/start, length, recording: entry {i} is frames {s[i]}..{s[i] + ln[i]} of recording "
                 f"{rec[i]}, expected frames within 0..{total} and a recording in 0..{R - 1}")
    ws, we = (ints(p) if have(p) else np.zeros(0, np.int64) for p in ("clips/word_start", "clips/word_end"))
    if ((ws < 0) | (we < ws) | (we > W)).any():
        i = int(np.flatnonzero((ws < 0) | (we < ws) | (we > W))[0])
        fail(f"clips/word_start, word_end: clip {i} has words {ws[i]}..{we[i]}, expected within 0..{W}")
    wr = ints("words/recording") if have("words/recording") else np.zeros(0, np.int64)
    if ((wr < 0) | (wr >= R)).any():
        fail(f"words/recording: expected recordings in 0..{R - 1}, got {int(wr[(wr < 0) | (wr >= R)][0])}")
    for path in ("audio/mean", "audio/std", "skeleton/offsets", "recordings/source_fps"):
        if not have(path):
            continue
        a = ints(path)
        if not np.isfinite(a).all():
            fail(f"{path}: expected finite values, got {a[~np.isfinite(a)][0]}")
    if have("audio/std") and (ints("audio/std") <= 0).any():
        fail("audio/std: expected positive standard deviations")
    rows = np.unique(np.linspace(0, F - 1, min(F, CHECK_SAMPLE_ROWS)).astype(np.int64))
    sample = sample or (lambda path, rows: h5[path][rows])
    for path in ("frames/pose_features", "frames/audio_features", "frames/joint_positions",
                 "frames/local_rotations", "frames/root_positions"):
        if not have(path) or F < 1:
            continue
        if path in MEAN_FIELDS:
            read_mean(h5, path, name)
        a = np.asarray(sample(path, rows))
        if not np.isfinite(a).all():
            r = int(rows[np.argwhere(~np.isfinite(a))[0][0]])
            fail(f"{path}: expected finite values, got a non-finite value at frame {r}")
        if path == "frames/local_rotations":
            norm = np.linalg.norm(a.astype(np.float64), axis=-1)
            if (np.abs(norm - 1.0) > 1e-2).any():
                r, j = (int(v) for v in np.argwhere(np.abs(norm - 1.0) > 1e-2)[0])
                fail(f"{path}: expected unit quaternions, got norm {norm[r, j]:.3g} at frame {int(rows[r])}, joint {j}")
    fr = sample("frames/recording", rows) if have("frames/recording") and F >= 1 else np.zeros(0, np.int64)
    if ((fr < 0) | (fr >= R)).any():
        fail(f"frames/recording: expected recordings in 0..{R - 1}, got {int(fr[(fr < 0) | (fr >= R)][0])}")
    B = (F + 63) // 64
    for group, want_shape, kind in ((CONTROLS_GROUP, (F,), "f"), (MASKS_GROUP, (B,), "u")):
        g = h5.get(group)
        for k in ([] if g is None else g):
            ds = g[k]
            if not isinstance(ds, h5py.Dataset):
                fail(f"{group}/{k}: expected a dataset, got a group (a name with '/'?); repair with "
                     f"`gesturedb masks DB remove {k}`" if group == MASKS_GROUP else f"{group}/{k}: expected a dataset")
            if ds.shape != want_shape or ds.dtype.kind != kind:
                fail(f"{group}/{k}: expected shape {want_shape} of kind {kind!r}, got {ds.dtype} {ds.shape}")


def shard_entries(h5, filename: str | os.PathLike | None = None) -> list[dict]:
    """The shard list of an index file (``[]`` for a single-file database), validated in form.

    Returns
    -------
    list of dict
        ``{"file": absolute path, "frames": (f0, f1), "token": str}`` in frame order.
    """
    if SHARDS_ATTR not in h5.attrs:
        return []
    name = os.fspath(filename) if filename is not None else h5.filename
    raw = _json_or(h5, SHARDS_ATTR, None)
    folder = os.path.dirname(os.path.abspath(name))
    out, f_end = [], 0
    if not isinstance(raw, list) or not raw:
        raise SchemaError(name, f"{SHARDS_ATTR}: expected a non-empty JSON list of shard files, got {str(raw)[:60]!r}")
    for i, e in enumerate(raw):
        ok = (isinstance(e, dict) and isinstance(e.get("file"), str) and isinstance(e.get("token"), str)
              and isinstance(e.get("frames"), list) and len(e["frames"]) == 2
              and all(isinstance(v, int) for v in e["frames"]))
        if not ok or os.path.basename(e["file"]) != e["file"] or e["frames"][0] != f_end or e["frames"][1] <= f_end:
            raise SchemaError(name, f"{SHARDS_ATTR}[{i}]: expected {{'file': a name beside the index, 'frames': "
                                    f"[{f_end}, f1 > {f_end}], 'token': str}}, got {str(e)[:80]!r}")
        f_end = e["frames"][1]
        out.append({"file": os.path.join(folder, e["file"]), "frames": tuple(e["frames"]), "token": e["token"]})
    return out


def check_shards(h5, filename: str | os.PathLike | None = None) -> None:
    """An index file's shards exist, are the parts it was written with, and cover its frames.

    A missing shard would otherwise read as fill values (HDF5 virtual datasets do not fail),
    so every shard file is opened here and its ``shard_of`` attribute compared with the index;
    and the virtual datasets' own mappings must name exactly those files
    (:func:`virtual_source_problem`), since those are what HDF5 reads.
    """
    name = os.fspath(filename) if filename is not None else h5.filename
    entries = shard_entries(h5, name)
    n_frames = int(h5.attrs.get("n_frames", -1))
    if entries[-1]["frames"][1] != n_frames:
        raise SchemaError(name, f"{SHARDS_ATTR}: expected shards covering frames 0..{n_frames}, got 0.."
                                f"{entries[-1]['frames'][1]}")
    for p in SHARDED_FIELDS:  # first: what HDF5 would read is what the list names
        if p in h5:
            problem = virtual_source_problem(h5[p], entries, p)
            if problem is not None:
                raise SchemaError(name, f"{p}: {problem}")
    for i, e in enumerate(entries):
        n = e["frames"][1] - e["frames"][0]
        shapes = {p: (n,) + h5[p].shape[1:] for p in SHARDED_FIELDS if p in h5}
        problem = shard_file_problem(e["file"], shard_expected(entries, i), shapes)
        if problem is not None:
            raise SchemaError(name, f"{SHARDS_ATTR}[{i}] ({os.path.basename(e['file'])}): {problem}")


def virtual_source_problem(ds, entries: list[dict], path: str) -> str | None:
    """What keeps a per-frame dataset of an index from mapping exactly its shards' rows, or None.

    The ``shards`` list is what the index says; the virtual-dataset mappings are what HDF5
    reads. Both must agree: the dataset is virtual, with one mapping per shard, in order,
    from dataset ``path`` of the shard file named in the list (beside the index) onto that
    shard's rows. Otherwise an index whose mappings name another file would read from it
    (or, for a file that is not HDF5, fail inside HDF5).
    """
    if not ds.is_virtual:
        return f"expected a virtual dataset over the {len(entries)} shard file(s), got a dataset stored in the index"
    maps = ds.virtual_sources()
    if len(maps) != len(entries):
        return f"expected {len(entries)} virtual-dataset mapping(s), one per shard file, got {len(maps)}"
    tail = tuple(ds.shape[1:])
    for i, (m, e) in enumerate(zip(maps, entries)):
        f0, f1 = e["frames"]
        want = os.path.basename(e["file"])
        if m.file_name != want or m.dset_name != path:
            got = f"{m.file_name[:200]}:{m.dset_name[:100]}"
            return (f"mapping {i}: expected {want}:{path} (shard {i + 1} of the index's list), got "
                    f"{got if got.isprintable() else repr(got)}")
        try:
            lo, hi = m.vspace.get_select_bounds()
            n = m.vspace.get_select_npoints()
        except (ValueError, RuntimeError):
            lo = hi = n = None
        full = (f0,) + (0,) * len(tail), (f1 - 1,) + tuple(d - 1 for d in tail)
        if (tuple(lo or ()), tuple(hi or ())) != full or n != (f1 - f0) * int(np.prod(tail, dtype=np.int64)):
            return f"mapping {i} ({want}): expected rows {f0}..{f1} of the dataset, got bounds {lo}..{hi}"
    return None


def shard_expected(entries: list[dict], i: int) -> dict:
    """The ``shard_of`` attribute shard ``i`` of :func:`shard_entries` must carry."""
    e = entries[i]
    return {"token": e["token"], "part": i + 1, "parts": len(entries), "frames": list(e["frames"])}


def shard_file_problem(path: str, expected: dict, shapes: dict[str, tuple]) -> str | None:
    """What keeps the file at ``path`` from being the shard ``expected`` (:func:`shard_expected`)
    with datasets of ``shapes`` (name -> shape), or None if it is that shard.

    Checked by the index when it is opened and again by every Dask worker that reads a shard
    (:mod:`gesturedb.db.shards`): a worker on another machine may see another copy of the folder.
    """
    h5py = _h5py()
    if not os.path.isfile(path):
        return f"shard file {path} is missing (an index needs every shard beside it)"
    try:
        with h5py.File(path, "r") as sh:
            of = _json_or(sh, SHARD_OF_ATTR, None)
            of = of if isinstance(of, dict) else None
            got_shapes = {p: sh[p].shape for p in shapes if p in sh}
    except OSError as exc:
        return f"cannot read the shard file {path} ({exc})"
    got = {k: (of or {}).get(k) for k in expected}
    if got != expected:
        return (f"expected the shard {expected} of this index, got {got} in {path} (a shard of another "
                f"sharding; shard the database again)")
    for p, shape in shapes.items():
        if got_shapes.get(p) != tuple(shape):
            return f"{p}: expected shape {tuple(shape)}, got {got_shapes.get(p, 'no dataset')}"
    return None


#: names of saved masks: an identifier the mask language can refer to, at most 64 characters
#: (no '/', which HDF5 would turn into nested groups, no '.', no spaces)
MASK_NAME_PATTERN = r"[A-Za-z_][A-Za-z0-9_]{0,63}"
#: names of recordings (file stems): no ',' (``--exclude`` separates with commas), no '/' and no control characters
RECORDING_NAME_PATTERN = r"[^,/\x00-\x1f\x7f]{1,255}"


def check_name(kind: str, name, pattern: str) -> str:
    """Return ``name`` if it matches ``pattern`` entirely, else raise :class:`ParameterError`."""
    import re

    if not isinstance(name, str) or not re.fullmatch(pattern, name):
        raise ParameterError(f"{kind}: expected a name matching {pattern}, got {name!r}")
    return name


def write_json_attr(obj, name: str, value: Any) -> None:
    obj.attrs[name] = json.dumps(value, sort_keys=True)


def _json_or(obj, name: str, bad: Any) -> Any:
    """A JSON attribute, or ``bad`` when it is not valid JSON (the caller's check names the field)."""
    try:
        return read_json_attr(obj, name, bad)
    except (TypeError, ValueError):
        return bad


def read_json_attr(obj, name: str, default: Any = None) -> Any:
    if name not in obj.attrs:
        return default
    return json.loads(obj.attrs[name])


def describe() -> str:
    """The schema as a Markdown table (the docs site's schema page and `gesturedb info --schema`)."""
    lines = [f"Schema version {SCHEMA_VERSION}.", "", "| dataset | dtype | shape | unit | meaning |", "|---|---|---|---|---|"]
    for f in FIELDS:
        shape = "(" + ", ".join(str(s) for s in f.shape) + ("," if len(f.shape) == 1 else "") + ")"
        lines.append(f"| `{f.path}` | {f.dtype} | {shape} | {f.unit} | {f.doc} |")
    lines += [
        f"| `{CONTROLS_GROUP}/<name>` | float32 | (F,) | attr `unit` | per-frame control feature |",
        f"| `{MASKS_GROUP}/<name>` | uint64 | (B,) | | packed bitset over frames (bit f&63 of word f>>6); attr `definition` |",
        f"| `{SUBDB_GROUP}/<word>/start,length` | int64 | (n,) | frame | keyword sub-database stretches (global frames); attr `definition` (JSON) |",
        f"| `{SUBDB_GROUP}/<word>/recording` | int32 | (n,) | | recording of each stretch |",
        f"| `{SUBDB_GROUP}/<word>/word_index` | int64 | (n,) | | the occurrence (index into `words/`) |",
        f"| `{SUBDB_GROUP}/<word>/mask` | uint64 | (B,) | | union of the stretches as a bitset over frames |",
        "",
        f"Dataset attribute `{MEAN_ATTR}` of {', '.join(f'`{p}`' for p in MEAN_FIELDS)}: float64, the mean over "
        "frames (numpy's float64 mean along axis 0, bit for bit), so `--init mean` reads no frames.",
        "",
        "Root attributes: " + "; ".join(f"`{k}` ({v})" for k, v in ROOT_ATTRS.items()) + ".",
    ]
    return "\n".join(lines)
