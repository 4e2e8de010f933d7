"""Training windows for the refiner (Habibie et al. 2022, Sec. 4, "Matching Database").

Real pairs: the database's own audio-gesture windows of ``window`` = 64 frames
with stride 5, never crossing a recording boundary. Fake inputs ``G_kNN``: the
k-NN synthesis of each window's own audio over the same database (one batched
kernel call, :func:`gesturedb.search.rank_sum_search_batch`), assembled exactly
as synthesis assembles it (seams inertialized, as in synthesis), so the refiner
trains on what it will be given. k = 1 for half of the windows and uniform in
2..15 for the other half; the initial pose is a random database frame.

What a window may not find: its own performance. Every segment of the window's
recording *and of its mirrored copy* (the same performance, reflected) that
overlaps the window or the ``window`` frames before and after it is excluded.
With several recordings that is a small hole; with one recording (and its
mirror) it is what keeps the search from copying the answer. The paper
excludes the whole recording; on a single-recording database that would leave
only the mirror, so the neighbourhood rule is used throughout (documented in
the checkpoint's ``data`` entry).

Everything here is numpy. Stored, the data is what it cannot recompute:
the fakes, one ``(C, window)`` block per window, in ``<checkpoint>.data.h5``
under the database's identity and the data's own settings (seed, window,
stride), so a second training run does not search again. The real windows and
their audio are the database's own frames: they are kept once per frame, not
once per window (a frame is in ``window / stride`` = 13 windows), and sliced
per batch. The fakes are read from the cache file through a memory map, so
training holds neither the fakes nor the real windows whole in memory (about
173 kB per window before: 20 GB at paper scale).

Making the fakes takes two passes: the self-search (one batched kernel call
per chunk of windows, or over shards on Dask workers) and the assembly of every
window's k-NN path, which is Python per window (about 8 ms each, 16 minutes
for the 120,000 windows of a paper-scale database on one core). The assembly
runs in chunks of windows on ``workers`` local processes or on the Dask
workers, each opening the database by its path; results are written as they
come, in window order, so the data does not depend on the scheduling.
"""
from __future__ import annotations

import hashlib
import os
import threading
from dataclasses import dataclass

import numpy as np

import gesturedb
from gesturedb.db import arrayfile
from gesturedb.db.cluster import check_on_worker, iter_on_cluster, worker_address
from gesturedb.db.shards import ShardedSearch
from gesturedb.db.workers import single_threaded_worker
from gesturedb.errors import InputFileError, ParameterError
from gesturedb.refiner.representation import moving_joints, to_channels
from gesturedb.search import PoseProjection, rank_sum_search_batch
from gesturedb.synth.assemble import assemble_frames
from gesturedb.synth.options import default_step

WINDOW = 64
STRIDE = 5
K_MAX = 15


def database_identity(db) -> str:
    """A short hash of what a refiner depends on: skeleton, frame count, fps and feature configuration."""
    h = hashlib.sha256()
    sk = db.skeleton
    h.update("|".join(sk.names).encode())
    h.update(np.asarray(sk.parents, dtype=np.int64).tobytes())
    # the widths from the datasets' shapes: reading the arrays for them would load the pose
    # features into every Dask worker that checks the identity (and into an index's client)
    Dp, Da = (db.frame_shape(k)[1] for k in ("pose_features", "audio_features"))
    h.update(f"{db.n_frames}|{db.fps}|{Dp}|{Da}".encode())
    h.update(np.asarray(db.audio_mean, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def feature_identity(db) -> dict:
    """What must match between a checkpoint and the database it refines for (skeleton and features)."""
    sk = db.skeleton
    return {
        "joint_names": list(sk.names),
        "parents": [int(p) for p in sk.parents],
        "fps": float(db.fps),
        "audio_channels": int(db.audio_features.shape[1] + db.audio_deltas.shape[1]),
        "n_mfcc": int(db.config.get("n_mfcc", 13)),
    }


@dataclass
class TrainingData:
    """Aligned training windows: the database's own frames, and one fake per window.

    Attributes
    ----------
    frame_audio : ndarray [shape=(F, A)], float32
        Standardised audio features and their deltas (A = 28) of every database frame.
    frame_real : ndarray [shape=(F, C)], float32
        The database's gesture channels of every frame (:func:`to_channels`).
    knn : ndarray or read-only memmap [shape=(W, C, window)], float32
        The k-NN synthesis of each window's audio (the generator's input).
    joints : ndarray [shape=(Jm,)], int64
        Joints in the channels (:func:`moving_joints`).
    starts : ndarray [shape=(W,)], int64
        Global first frame of every window.
    ks : ndarray [shape=(W,)], int64
        The k used for each fake.
    val : ndarray [shape=(W,)], bool, optional
        Validation windows (:func:`split_windows`): never sampled for training. None: all train.
    """

    frame_audio: np.ndarray
    frame_real: np.ndarray
    knn: np.ndarray
    joints: np.ndarray
    starts: np.ndarray
    ks: np.ndarray
    val: np.ndarray | None = None

    @property
    def train_windows(self) -> np.ndarray:
        """(n,) int64 indices of the windows training samples from."""
        return np.flatnonzero(~self.val) if self.val is not None else np.arange(self.n_windows)

    @property
    def val_windows(self) -> np.ndarray:
        """(n,) int64 indices of the validation windows (empty without a split)."""
        return np.flatnonzero(self.val) if self.val is not None else np.zeros(0, np.int64)

    @property
    def n_windows(self) -> int:
        return int(self.knn.shape[0])

    @property
    def channels(self) -> int:
        """C, gesture channels per frame."""
        return int(self.knn.shape[1])

    @property
    def audio_channels(self) -> int:
        """A, audio channels per frame."""
        return int(self.frame_audio.shape[1])

    @property
    def window(self) -> int:
        return int(self.knn.shape[2])

    def _windows(self, per_frame: np.ndarray, idx) -> np.ndarray:
        frames = self.starts[np.asarray(idx, dtype=np.int64)][:, None] + np.arange(self.window)
        return np.ascontiguousarray(per_frame[frames].transpose(0, 2, 1))

    def audio(self, idx) -> np.ndarray:
        """(n, A, window) float32: the audio of windows ``idx`` (n,)."""
        return self._windows(self.frame_audio, idx)

    def real(self, idx) -> np.ndarray:
        """(n, C, window) float32: the database's own gesture channels of windows ``idx`` (n,)."""
        return self._windows(self.frame_real, idx)

    def fake(self, idx) -> np.ndarray:
        """(n, C, window) float32: the k-NN syntheses of windows ``idx`` (n,)."""
        return np.ascontiguousarray(self.knn[np.asarray(idx, dtype=np.int64)])


def frame_arrays(db, joints: np.ndarray, *, chunk: int = 1 << 15) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame audio (F, A) and gesture channels (F, C) float32 of a database.

    Converted ``chunk`` frames at a time: the whole database's rotation matrices
    in float64 would be 2.4 GB at paper scale.
    """
    audio = np.concatenate([np.asarray(db.audio_features, dtype=np.float32),
                            np.asarray(db.audio_deltas, dtype=np.float32)], axis=1)
    rot = db.local_rotations
    F = int(rot.shape[0])
    real = np.empty((F, 6 * len(joints)), np.float32)
    for a in range(0, F, chunk):
        real[a:a + chunk] = to_channels(rot[a:a + chunk], joints)
    return audio, real


# -- the cache: <checkpoint>.data.h5 ---------------------------------------------------
CACHE_FORMAT = 3  # 1: one npz (before 2026-11); 2: no validation split (before issue 40)


def cache_settings(db, *, seed: int, window: int, stride: int, val_fraction: float = 0.0) -> dict:
    """What a cache must have been made with to be reused."""
    return {"format": CACHE_FORMAT, "identity": database_identity(db), "seed": int(seed),
            "window": int(window), "stride": int(stride), "val_fraction": float(val_fraction)}


def load_cache(path, db, settings: dict) -> TrainingData | None:
    """The cached training data, or None when there is none, or it was made for another
    database or with other settings, or it cannot be read (it is then made again).

    The fakes stay on disk (a read-only memory map of the file's contiguous dataset).
    A cache made for this database whose content is wrong (a window or joint outside the
    database, a non-finite fake, which made every weight NaN) is refused with an
    :class:`InputFileError` naming the file and the dataset.
    """
    path = os.fspath(path)
    attrs = arrayfile.read_attrs(path)
    if attrs is None or any(attrs.get(k) != v for k, v in settings.items()):
        return None
    got = arrayfile.read(path, ("starts", "ks", "joints", "val"), "knn")
    if got is None:
        return None
    arrays, knn = got
    starts, ks, joints = (arrays[k].astype(np.int64, copy=False) for k in ("starts", "ks", "joints"))
    val = arrays["val"].astype(bool, copy=False)
    shape = (len(starts), 6 * len(joints), int(settings["window"]))
    if knn.shape != shape or knn.dtype != np.float32 or ks.shape != starts.shape or val.shape != starts.shape:
        return None
    _check_cache(path, db, knn, starts, ks, joints, int(settings["window"]))
    want = split_windows(db, starts, float(settings["val_fraction"]), window=int(settings["window"]))
    if not np.array_equal(val, want):
        raise InputFileError(path, "val: the validation windows differ from the split of the database's "
                                   "recordings; delete the file and the training data is made again")
    audio, real = frame_arrays(db, joints)
    return TrainingData(frame_audio=audio, frame_real=real, knn=knn, joints=joints, starts=starts, ks=ks, val=val)


def _check_cache(path: str, db, knn, starts: np.ndarray, ks: np.ndarray, joints: np.ndarray, window: int,
                 *, chunk: int = 256) -> None:
    """Refuse a cache whose windows, k, joints or fakes could not have been made from ``db``."""
    F, J = int(db.n_frames), len(db.skeleton.names)

    def bad(field, problem):
        return InputFileError(path, f"{field}: {problem}; delete the file and the training data is made again")

    if starts.ndim != 1 or (starts.size and not (starts.min() >= 0 and starts.max() <= F - window)):
        raise bad("starts", f"expected first frames from 0 to {F - window} (windows of {window} frames in "
                            f"{F}), got {starts.min() if starts.min() < 0 else starts.max()}")
    if ks.size and not (ks.min() >= 1 and ks.max() <= K_MAX):
        raise bad("ks", f"expected k from 1 to {K_MAX}, got {ks.min() if ks.min() < 1 else ks.max()}")
    if joints.ndim != 1 or joints.size == 0 or not (joints.min() >= 0 and joints.max() < J) \
            or np.any(np.diff(joints) <= 0):
        raise bad("joints", f"expected ascending joint indices from 0 to {J - 1}, got {joints[:8].tolist()}")
    for a in range(0, knn.shape[0], chunk):  # a chunk at a time: the fakes stay on disk
        block = np.asarray(knn[a:a + chunk])
        finite = np.isfinite(block)
        if not finite.all():
            w, c, t = (int(i) for i in np.argwhere(~finite)[0])
            raise bad("knn", f"expected finite values, got {block[w, c, t]} in window {a + w} (channel {c}, "
                             f"frame {t})")


def _worker_database(path):
    """The database at ``path``, opened once per worker process (its arrays load on first use).

    A Dask worker may run tasks of two trainings in threads at once: the last two
    databases stay open, and one that drops out is closed by the garbage collector
    once no task holds it any more.
    """

    st = os.stat(path)
    key = (path, st.st_mtime_ns, st.st_size)
    with _OPEN_LOCK:
        db = _OPEN.pop(key, None) or gesturedb.open(path)
        _OPEN[key] = db  # most recent last
        while len(_OPEN) > 2:
            _OPEN.pop(next(iter(_OPEN)))
        return db


_OPEN: dict = {}
_OPEN_LOCK = threading.Lock()


def assemble_windows(db, frame_maps: np.ndarray, seams, joints: np.ndarray) -> np.ndarray:
    """The gesture channels of k-NN paths assembled as synthesis assembles them.

    Parameters
    ----------
    db : Database, or the path of one (opened once per process: the form Dask and
        local worker processes are given)
    frame_maps : ndarray [shape=(n, window)], int64
        Database frame of every output frame of each path.
    seams : sequence of n ndarray, int64
        Output frame where each window of a path starts (the first is 0).
    joints : ndarray [shape=(Jm,)], int64

    Returns
    -------
    ndarray [shape=(n, 6 Jm, window)], float32
    """

    if isinstance(db, (str, os.PathLike)):
        db = _worker_database(os.fspath(db))
    # Load what the assembly reads (a synthesis reads rows through Database.rows
    # instead): thousands of windows read from memory, and forked workers inherit
    # the arrays rather than reading the HDF5 file through the parent's handle.
    for name in ("local_rotations", "root_positions", "frame_recording"):
        getattr(db, name)
    out = np.empty((len(frame_maps), 6 * len(joints), frame_maps.shape[1]), np.float32)
    for i in range(len(frame_maps)):
        motion = assemble_frames(db, frame_maps[i], seams[i])
        out[i] = to_channels(motion.rotations, joints).T
    return out


def _assemble_task(args):
    """:func:`assemble_windows` on a Dask worker, which opens the database by the client's
    path: on another machine that may be another copy, so it must be the client's."""
    path, identity, *rest = args
    check_on_worker(path, "the database")
    db = _worker_database(path)
    if database_identity(db) != identity:
        raise InputFileError(path, f"on Dask worker {worker_address()}: expected the database the client opened "
                                   f"(identity {identity}), got another one ({db.n_frames} frames, identity "
                                   f"{database_identity(db)}): every worker must see the same file at the same "
                                   f"path (a shared or copied folder)")
    return assemble_windows(db, *rest)


def window_starts(db, *, window: int = WINDOW, stride: int = STRIDE) -> np.ndarray:
    """Global first frames of all windows that fit inside one recording, ``stride`` apart."""
    out = []
    for r in db.recordings:
        if r.n_frames >= window:
            out.append(r.start_frame + np.arange(0, r.n_frames - window + 1, stride))
    if not out:
        raise ParameterError(f"database {db.path}: no recording has {window} frames for a training window")
    return np.concatenate(out).astype(np.int64)


def held_out_from(db, val_fraction: float) -> np.ndarray:
    """(R,) int64: the first frame (within each recording) of its held-out last ``val_fraction``.

    The cut is taken from the end of each recording's *performance*: a mirrored copy
    (``NAME~mirror``) has its source's length, so it loses the same stretch, and no
    validation motion reaches training reflected. ``val_fraction`` 0 holds nothing back
    (every cut is the recording's length).
    """
    f = float(val_fraction)
    if not (np.isfinite(f) and 0 <= f < 1):
        raise ParameterError(f"val_fraction: expected a fraction in [0, 1), got {val_fraction!r}")
    perf = _same_performance(db)
    n = np.array([r.n_frames for r in db.recordings], dtype=np.int64)
    shortest = {p: n[perf == p].min() for p in np.unique(perf)}  # a performance's copies: one cut
    return np.array([n[i] if f == 0 else int(np.floor(shortest[p] * (1 - f))) for i, p in enumerate(perf)],
                    dtype=np.int64)


def split_windows(db, starts: np.ndarray, val_fraction: float, *, window: int = WINDOW) -> np.ndarray:
    """(W,) bool: which windows validate (they lie wholly in their recording's held-out end,
    :func:`held_out_from`). :func:`usable_windows` drops the windows that straddle a cut."""
    cut = held_out_from(db, val_fraction)
    rec = np.asarray(db.frame_recording[starts], dtype=np.int64)
    first = np.array([r.start_frame for r in db.recordings], dtype=np.int64)
    return (np.asarray(starts, dtype=np.int64) - first[rec]) >= cut[rec]


def usable_windows(db, starts: np.ndarray, val_fraction: float, *, window: int = WINDOW) -> np.ndarray:
    """(W,) bool: windows wholly before their recording's cut (training) or wholly after it (validation)."""
    cut = held_out_from(db, val_fraction)
    rec = np.asarray(db.frame_recording[starts], dtype=np.int64)
    a = np.asarray(starts, dtype=np.int64) - np.array([r.start_frame for r in db.recordings], dtype=np.int64)[rec]
    return (a + window <= cut[rec]) | (a >= cut[rec])


def _same_performance(db) -> np.ndarray:
    """(R,) index of the performance each recording belongs to (a mirrored copy shares its source's)."""
    base = [r.name.removesuffix("~mirror") for r in db.recordings]
    ids = {b: i for i, b in enumerate(dict.fromkeys(base))}
    return np.array([ids[b] for b in base], dtype=np.int64)


def exclusion(db, starts: np.ndarray, *, window: int = WINDOW, held_out: np.ndarray | None = None,
              val: np.ndarray | None = None) -> np.ndarray:
    """(W, M) bool: segments each window may not copy (its neighbourhood in its own performance).

    With ``held_out`` ((R,) first held-out frame per recording, :func:`held_out_from`) and
    ``val`` ((W,) bool), a training window (``~val``) may not copy any segment that reaches
    into a held-out stretch either: its fake, the generator's input, then holds no
    validation frame. Validation windows may copy training frames, as synthesis does.
    """
    seg = db.chunks
    perf = _same_performance(db)
    recs = db.recordings
    rec_start = np.array([r.start_frame for r in recs], dtype=np.int64)
    seg_rec = np.asarray(seg.recording, dtype=np.int64)
    seg_a = np.asarray(seg.start, dtype=np.int64) - rec_start[seg_rec]   # frame within its recording
    seg_b = seg_a + np.asarray(seg.length, dtype=np.int64)
    w_rec = np.asarray(db.frame_recording[starts], dtype=np.int64)
    w_a = starts - rec_start[w_rec]
    lo, hi = w_a - window, w_a + 2 * window
    same = perf[seg_rec][None, :] == perf[w_rec][:, None]
    overlap = (seg_b[None, :] > lo[:, None]) & (seg_a[None, :] < hi[:, None])
    out = same & overlap
    if held_out is not None:
        into = seg_b > np.asarray(held_out, dtype=np.int64)[seg_rec]  # (M,) the segment reaches a held-out frame
        train = ~np.asarray(val, dtype=bool) if val is not None else np.ones(len(starts), bool)
        out |= train[:, None] & into[None, :]
    return np.ascontiguousarray(out)


def make_training_data(db, *, seed: int = 0, window: int = WINDOW, stride: int = STRIDE,
                       progress=None, scheduler=None, parts: int = 2, chunk: int | None = None,
                       workers: int = 1, cache=None, val_fraction: float = 0.0) -> TrainingData:
    """Search the database for its own audio and pair every window with its k-NN synthesis.

    With a Dask ``scheduler`` (a ``distributed.Client``, ``"local:N"`` or ``"tcp://HOST:PORT"``,
    :mod:`gesturedb.db.cluster`) the self-search runs over ``parts`` shards resident on its
    workers (:meth:`gesturedb.db.shards.ShardedSearch.search_batch`; an index file
    over its own shard files) and the assembly runs on the same workers; without
    one, the assembly runs on ``workers`` local processes. Either way the data is
    the same. The windows are searched ``chunk`` at a time (default: as many as
    keep the windows x segments exclusion matrix under about 256 MB); the queries
    are independent, so any chunk gives the same data. ``progress(stage, done,
    total)`` is called after each chunk of the search (stage ``"search"``) and of
    the assembly (``"assembly"``).

    With ``cache`` (a path) the fakes are written straight into that HDF5 file
    (through a temporary sibling renamed at the end, :func:`load_cache` reads it)
    and the result reads them from it: nothing of size windows x channels x frames
    is held in memory. Without it they are returned in memory.

    ``val_fraction``: the last fraction of every recording (and of its mirrored copy) is
    held back for validation (:func:`split_windows`); windows that straddle the cut are
    left out, and training windows' fakes copy nothing from a held-out stretch
    (:func:`exclusion`), so no validation frame reaches training.
    """

    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ParameterError(f"workers: expected an int >= 1; got {workers!r}")
    rng = np.random.default_rng(seed)
    starts = window_starts(db, window=window, stride=stride)
    starts = starts[usable_windows(db, starts, val_fraction, window=window)]
    val = split_windows(db, starts, val_fraction, window=window)
    held = held_out_from(db, val_fraction) if val_fraction > 0 else None
    if val_fraction > 0 and (val.all() or not val.any()):
        raise ParameterError(f"val_fraction: {val_fraction:g} leaves {int((~val).sum())} training and "
                             f"{int(val.sum())} validation windows of {window} frames in {db.path}; expected some "
                             f"of each (recordings of at least {window} frames on each side of the cut)")
    W = len(starts)
    audio_f = np.asarray(db.audio_features)
    queries = [np.ascontiguousarray(audio_f[a:a + window]) for a in starts]
    ks = np.where(np.arange(W) % 2 == 0, 1, rng.integers(2, K_MAX + 1, size=W)).astype(np.int64)
    rng.shuffle(ks)
    init = np.ascontiguousarray(db.pose_features[rng.integers(0, db.n_frames, size=W)])
    step = default_step(db.fps)  # the synthesis' own step (8 frames at 15 fps), whatever the frame rate
    seg = db.chunks
    seg_start = np.ascontiguousarray(seg.start, dtype=np.int64)
    seg_len = np.ascontiguousarray(seg.length, dtype=np.int64)
    per = chunk if chunk is not None else max(256, (256 << 20) // max(1, seg_start.shape[0]))
    if isinstance(per, bool) or not isinstance(per, (int, np.integer)) or per < 1:
        raise ParameterError(f"chunk: expected None or an int >= 1; got {chunk!r}")
    if scheduler is not None:
        sharded = ShardedSearch.for_database(db, seg_start, seg_len, scheduler=scheduler, parts=parts)

        def search_chunk(q, p, k, ex):
            return sharded.search_batch(q, p, step=step, k=k, exclude=ex)
    else:
        sharded = None
        # the batch's pose filter then reads 24 projected columns instead of 96 (same
        # results); skipped, as in Searcher, where it would keep a quarter of the rows
        proj = PoseProjection(db.pose_features)
        proj = proj if proj.keep_fraction < 0.25 else None

        def search_chunk(q, p, k, ex):
            return rank_sum_search_batch(db.pose_features, db.audio_features, seg_start, seg_len, q, p,
                                         step=step, k=k, exclude=ex, pose_proj=proj)
    # the paths only (a window's frame map and seams, about 600 bytes): the motion is assembled below
    frame_maps = np.empty((W, window), np.int64)
    seams = []
    try:
        for a in range(0, W, per):
            b = min(W, a + per)
            for i, res in enumerate(search_chunk(queries[a:b], init[a:b], ks[a:b],
                                                 exclusion(db, starts[a:b], window=window, held_out=held,
                                                           val=val[a:b])), a):
                frame_maps[i] = res.frame_map()
                seams.append(np.asarray(res.out_frames, dtype=np.int64))
            if progress is not None:
                progress("search", b, W)
    finally:
        if sharded is not None:
            sharded.close()
    del queries
    joints = moving_joints(db.local_rotations)
    shape = (W, 6 * len(joints), window)
    if cache is None:
        knn = np.empty(shape, np.float32)
        _assemble_all(db, frame_maps, seams, joints, knn, progress=progress, scheduler=scheduler, workers=workers)
        audio, real = frame_arrays(db, joints)
        return TrainingData(frame_audio=audio, frame_real=real, knn=knn, joints=joints, starts=starts, ks=ks,
                            val=val)
    cache = os.fspath(cache)
    settings = cache_settings(db, seed=seed, window=window, stride=stride, val_fraction=val_fraction)
    content = ("fakes of the gesturedb refiner's training windows: knn[w] is the k-NN synthesis (channels x "
               "frames) of the audio of frames starts[w] + 0..window-1")
    # a temporary sibling renamed on success, removed on any failure, Ctrl-C or SIGTERM
    arrayfile.write(cache, attrs={**settings, "content": content},
                    arrays={"starts": starts, "ks": ks, "joints": joints, "val": val}, block="knn", shape=shape,
                    dtype=np.float32,
                    fill=lambda knn: _assemble_all(db, frame_maps, seams, joints, knn, progress=progress,
                                                   scheduler=scheduler, workers=workers))
    data = load_cache(cache, db, settings)
    if data is None:  # pragma: no cover - the file was just written
        raise InputFileError(cache, "the training-data cache just written could not be read back")
    return data


def _assemble_all(db, frame_maps, seams, joints, out, *, progress, scheduler, workers, chunk: int = 32) -> None:
    """Assemble every window's path into ``out[w]`` (an array or an HDF5 dataset), in
    chunks of ``chunk`` windows: in this process, on ``workers`` local processes, or
    on the Dask ``scheduler``'s workers (which open the database by its path)."""
    W = len(frame_maps)
    pieces = [(a, min(W, a + chunk)) for a in range(0, W, chunk)]
    done = 0

    def store(k, block):
        nonlocal done
        a, b = pieces[k]
        out[a:b] = block
        done += b - a
        if progress is not None:
            progress("assembly", done, W)

    if scheduler is None and (workers == 1 or len(pieces) == 1):
        for k, (a, b) in enumerate(pieces):
            store(k, assemble_windows(db, frame_maps[a:b], seams[a:b], joints))
        return
    if scheduler is not None:
        path, identity = os.path.abspath(db.path), database_identity(db)
        tasks = [(path, identity, frame_maps[a:b], seams[a:b], joints) for a, b in pieces]
        for k, block in iter_on_cluster(_assemble_task, tasks, scheduler):
            store(k, block)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # The first chunk in this process loads every array the assembly reads; forked
    # workers then share them (copy-on-write: a paper-scale database's rotations
    # are a gigabyte) and never touch the HDF5 file. Fork, not spawn: spawn would
    # re-import the caller's main module, which breaks scripts without a main guard.
    store(0, assemble_windows(db, frame_maps[:pieces[0][1]], seams[:pieces[0][1]], joints))
    if "fork" not in multiprocessing.get_all_start_methods():  # pragma: no cover - Windows
        for k, (a, b) in enumerate(pieces[1:], 1):
            store(k, assemble_windows(db, frame_maps[a:b], seams[a:b], joints))
        return
    _FORKED.update(db=db, frame_maps=frame_maps, seams=seams, joints=joints, pieces=pieces)
    try:
        with ProcessPoolExecutor(max_workers=min(workers, len(pieces) - 1), mp_context=multiprocessing.get_context("fork"),
                                 initializer=single_threaded_worker, initargs=(os.getpid(),)) as ex:
            for k, block in enumerate(ex.map(_assemble_forked, range(1, len(pieces))), 1):
                store(k, block)
    finally:
        _FORKED.clear()


_FORKED: dict = {}  # what forked assembly workers inherit


def _assemble_forked(k: int) -> np.ndarray:
    f = _FORKED
    a, b = f["pieces"][k]
    return assemble_windows(f["db"], f["frame_maps"][a:b], f["seams"][a:b], f["joints"])
