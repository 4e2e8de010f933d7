"""Training windows for the refiner (Habibie et al. 2022, Sec. 4, "Matching Database").

Real pairs: the database's own audio-gesture windows of ``window`` = 64 frames
with stride 5, never crossing a recording boundary. Fake inputs ``G_kNN``: the
k-NN synthesis of each window's own audio over the same database (one batched
kernel call, :func:`gesturedb.search.rank_sum_search_batch`), assembled exactly
as synthesis assembles it (seam cross-fades and smoothing), so the refiner
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

Everything here is numpy; the result is cached beside the checkpoint
(``<checkpoint>.data.npz``) under the database's identity, so a second
training run does not search again.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass

import numpy as np

from gesturedb.errors import ParameterError
from gesturedb.io.atomic import atomic_open
from gesturedb.refiner.representation import moving_joints, to_channels

WINDOW = 64
STRIDE = 5
K_MAX = 15


def database_identity(db) -> str:
    """A short hash of what a refiner depends on: skeleton, frame count, fps and feature configuration."""
    h = hashlib.sha256()
    sk = db.skeleton
    h.update("|".join(sk.names).encode())
    h.update(np.asarray(sk.parents, dtype=np.int64).tobytes())
    h.update(f"{db.n_frames}|{db.fps}|{db.pose_features.shape[1]}|{db.audio_features.shape[1]}".encode())
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
    """Aligned training windows.

    Attributes
    ----------
    audio : ndarray [shape=(W, 28, window)], float32
        Standardised audio features and their deltas.
    real : ndarray [shape=(W, C_g, window)], float32
        The database's own gesture channels.
    knn : ndarray [shape=(W, C_g, window)], float32
        The k-NN synthesis of the same audio (the generator's input).
    joints : ndarray [shape=(Jm,)], int64
        Joints in the channels (:func:`moving_joints`).
    starts : ndarray [shape=(W,)], int64
        Global first frame of every window.
    ks : ndarray [shape=(W,)], int64
        The k used for each fake.
    """

    audio: np.ndarray
    real: np.ndarray
    knn: np.ndarray
    joints: np.ndarray
    starts: np.ndarray
    ks: np.ndarray

    def save(self, path, identity: str) -> None:
        # a temporary sibling with a unique name (two trainings sharing a cache never write one file)
        with atomic_open(path, "wb") as f:
            np.savez(f, identity=np.array(identity), **{k: getattr(self, k) for k in
                     ("audio", "real", "knn", "joints", "starts", "ks")})

    @classmethod
    def load(cls, path, identity: str) -> "TrainingData | None":
        """The cached windows, or None when there is no cache or it was made for another database."""
        if not os.path.isfile(path):
            return None
        with np.load(path, allow_pickle=False) as z:
            if str(z["identity"]) != identity:
                return None
            return cls(**{k: z[k] for k in ("audio", "real", "knn", "joints", "starts", "ks")})


def window_starts(db, *, window: int = WINDOW, stride: int = STRIDE) -> np.ndarray:
    """Global first frames of all windows that fit inside one recording, ``stride`` apart."""
    out = []
    for r in db.recordings:
        if r.n_frames >= window:
            out.append(r.start_frame + np.arange(0, r.n_frames - window + 1, stride))
    if not out:
        raise ParameterError(f"database {db.path}: no recording has {window} frames for a training window")
    return np.concatenate(out).astype(np.int64)


def _same_performance(db) -> np.ndarray:
    """(R,) index of the performance each recording belongs to (a mirrored copy shares its source's)."""
    base = [r.name.removesuffix("~mirror") for r in db.recordings]
    ids = {b: i for i, b in enumerate(dict.fromkeys(base))}
    return np.array([ids[b] for b in base], dtype=np.int64)


def exclusion(db, starts: np.ndarray, *, window: int = WINDOW) -> np.ndarray:
    """(W, M) bool: segments each window may not copy (its neighbourhood in its own performance)."""
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
    return np.ascontiguousarray(same & overlap)


def make_training_data(db, *, seed: int = 0, window: int = WINDOW, stride: int = STRIDE,
                       progress=None, client=None, parts: int = 2, chunk: int | None = None) -> TrainingData:
    """Search the database for its own audio and pair every window with its k-NN synthesis.

    With a Dask ``client`` the self-search runs over ``parts`` shards resident on its
    workers (:meth:`gesturedb.db.shards.ShardedSearch.search_batch`; an index file
    over its own shard files): the same windows, so the same training data.
    The windows are searched ``chunk`` at a time (default: as many as keep the
    windows x segments exclusion matrix under about 256 MB); the queries are
    independent, so any chunk gives the same data. ``progress(stage, done,
    total)`` is called after each chunk of the search (stage ``"search"``) and
    each assembled window (``"assembly"``).
    """
    from gesturedb.search import PoseProjection, rank_sum_search_batch
    from gesturedb.synth.assemble import assemble_frames

    rng = np.random.default_rng(seed)
    starts = window_starts(db, window=window, stride=stride)
    W = len(starts)
    audio_f = np.asarray(db.audio_features)
    deltas = np.asarray(db.audio_deltas)
    queries = [np.ascontiguousarray(audio_f[a:a + window]) for a in starts]
    ks = np.where(np.arange(W) % 2 == 0, 1, rng.integers(2, K_MAX + 1, size=W)).astype(np.int64)
    rng.shuffle(ks)
    init = np.ascontiguousarray(db.pose_features[rng.integers(0, db.n_frames, size=W)])
    seg = db.chunks
    seg_start = np.ascontiguousarray(seg.start, dtype=np.int64)
    seg_len = np.ascontiguousarray(seg.length, dtype=np.int64)
    per = chunk if chunk is not None else max(256, (256 << 20) // max(1, seg_start.shape[0]))
    if isinstance(per, bool) or not isinstance(per, (int, np.integer)) or per < 1:
        raise ParameterError(f"chunk: expected None or an int >= 1; got {chunk!r}")
    if client is not None:
        from gesturedb.db.shards import ShardedSearch

        sharded = ShardedSearch.for_database(db, seg_start, seg_len, client=client, parts=parts)

        def search_chunk(q, p, k, ex):
            return sharded.search_batch(q, p, step=8, k=k, exclude=ex)
    else:
        sharded = None
        # the batch's pose filter then reads 24 projected columns instead of 96 (same
        # results); skipped, as in Searcher, where it would keep a quarter of the rows
        proj = PoseProjection(db.pose_features)
        proj = proj if proj.keep_fraction < 0.25 else None

        def search_chunk(q, p, k, ex):
            return rank_sum_search_batch(db.pose_features, db.audio_features, seg_start, seg_len, q, p,
                                         step=8, k=k, exclude=ex, pose_proj=proj)
    results = []
    try:
        for a in range(0, W, per):
            b = min(W, a + per)
            results += search_chunk(queries[a:b], init[a:b], ks[a:b], exclusion(db, starts[a:b], window=window))
            if progress is not None:
                progress("search", b, W)
    finally:
        if sharded is not None:
            sharded.close()
    joints = moving_joints(db.local_rotations)
    rot_all = np.asarray(db.local_rotations)
    C = 6 * len(joints)
    real = np.empty((W, C, window), np.float32)
    knn = np.empty((W, C, window), np.float32)
    aud = np.empty((W, audio_f.shape[1] + deltas.shape[1], window), np.float32)
    for i, (a, res) in enumerate(zip(starts, results)):
        real[i] = to_channels(rot_all[a:a + window], joints).T
        motion = assemble_frames(db, res.frame_map(), np.asarray(res.out_frames, dtype=np.int64))
        knn[i] = to_channels(motion.rotations, joints).T
        aud[i] = np.concatenate([audio_f[a:a + window], deltas[a:a + window]], axis=1).T
        if progress is not None:
            progress("assembly", i + 1, W)
    return TrainingData(audio=aud, real=real, knn=knn, joints=joints, starts=starts, ks=ks)
