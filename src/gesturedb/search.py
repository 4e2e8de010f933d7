"""Rank-sum motion-matching search: the Python face of the C++ core.

Implements Habibie et al. 2022, Sec. 3.1, exactly as specified in
``../shared/spec/search.md``. Every N output frames one window of N database
frames is chosen: per segment, the allowed window whose entry pose is nearest
to the previous pose (or whose audio is nearest to the query, with
``preselect="audio"``) is pre-selected; the pre-selected windows are ranked by
pose distance and by audio distance, and the one with the k-th smallest rank
sum is copied to the output.

The heavy lifting is in ``gesturedb._core`` (SIMD kernels chosen at run time,
threads, the GIL released). This module validates every argument and turns
the core's raw arrays into :class:`StepResult` / :class:`SearchResult`.

Terms used throughout (shapes in brackets):

- ``pose`` [F, Dp] float32, ``audio`` [F, Da] float32: per-frame features of the
  whole database, C-contiguous. They are never copied or cast (they can be
  hundreds of megabytes): pass them as stored.
- ``seg_start``, ``seg_len`` [M] int64: segment ``m`` covers frames
  ``seg_start[m] .. seg_start[m] + seg_len[m] - 1``.
- A candidate ``(m, s)`` with ``1 <= s <= seg_len[m] - n`` is the window of
  ``n`` frames starting at global frame ``g = seg_start[m] + s``; its entry frame
  ``g - 1`` is the frame compared with the previous pose.
- ``allowed``: packed bitset over database frames, uint64 words, bit ``f & 63``
  of word ``f >> 6`` (see :mod:`gesturedb.control`); a window is allowed iff its
  first and last frame are.

Non-finite database features are not checked (that would read the whole
database on every call); a NaN distance loses every comparison.
"""
from __future__ import annotations

import numbers
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np

from gesturedb.errors import ParameterError, SearchError
from gesturedb.projection import HalfPose, PoseProjection

__all__ = [
    "StepResult",
    "SearchResult",
    "HalfPose",
    "PoseProjection",
    "rank_sum_step",
    "rank_sum_search",
    "rank_sum_search_batch",
    "blocked_min_queries",
    "kernels",
    "get_simd",
    "set_simd",
    "simd",
]

PRESELECT = ("pose", "audio")
#: N, the frames one search step copies: the paper's 8 at its 15 fps (Habibie et al. 2022, Sec. 3.1).
#: The kernel's default; a synthesis steps as often in time at any frame rate
#: (:func:`gesturedb.synth.options.default_step`).
STEP_FRAMES = 8


def blocked_min_queries(threads: int | None = None) -> int:
    """Queries from which ``method="auto"`` takes the blocked path (AVX2 / AVX-512; the scalar
    kernels never do) with ``threads`` threads (default: the CPUs this process may use).

    The blocked path runs a block of queries per thread; it pays off once each block holds the
    kernel's minimum (3 queries: at 617k frames a block of 3 costs 0.85-0.9 of their 3 single
    passes, one of 2 as much as 2 passes; benchmarks/RESULTS.md, "Narrow panels").
    """
    return int(_core().blocked_min_queries(threads if threads is not None else 0))


def _core():
    try:
        # local on purpose: a missing compiled kernel becomes the build hint below, not a failed import
        import gesturedb._core as core
    except ImportError as exc:  # pragma: no cover - depends on the build
        raise ImportError(
            "gesturedb._core is not built: run `python setup.py build_ext --inplace` "
            f"in the repository or `pip install .` ({exc})"
        ) from exc
    return core


# --------------------------------------------------------------------------
# results


@dataclass(frozen=True)
class StepResult:
    """The window chosen by one search step.

    Attributes
    ----------
    segment : int
        Segment index ``m``.
    start : int
        Offset ``s`` of the window in its segment (``>= 1``).
    frame : int
        Global database frame ``g = seg_start[m] + s`` of the window's first frame.
    length : int
        Number of frames ``n`` in the window.
    pose_dist : float
        ``||P[g-1] - prev||^2``, squared feature units.
    audio_dist : float
        Cosine distance ``1 - cos(query window, audio window)``, in [0, 2].
    pose_rank, audio_rank : int
        0-based ranks of the segment among the pre-selected ones.
    rank : int
        ``pose_rank + audio_rank``, the rank sum that orders the choice.
    n_candidates : int
        Segments that had an allowed candidate at this step.
    """

    segment: int
    start: int
    frame: int
    length: int
    pose_dist: float
    audio_dist: float
    pose_rank: int
    audio_rank: int
    rank: int
    n_candidates: int


@dataclass(frozen=True, eq=False)
class SearchResult:
    """All steps of one search; every array has shape (S,), S = ceil(T / step).

    Attributes
    ----------
    segments, starts, frames, lengths : ndarray [shape=(S,)], int64
        Chosen segment ``m``, offset ``s``, global first frame ``g`` and window
        length ``n`` of every step.
    out_frames : ndarray [shape=(S,)], int64
        Output frame ``t`` where each step's window is placed.
    pose_dist, audio_dist : ndarray [shape=(S,)], float64
        Distances of the chosen candidates (see :class:`StepResult`).
    pose_rank, audio_rank : ndarray [shape=(S,)], int64
        Their 0-based ranks.
    n_candidates : ndarray [shape=(S,)], int64
        Segments left after pre-selection at each step.
    n_frames : int
        Number of output frames T.
    """

    segments: np.ndarray
    starts: np.ndarray
    frames: np.ndarray
    lengths: np.ndarray
    out_frames: np.ndarray
    pose_dist: np.ndarray
    audio_dist: np.ndarray
    pose_rank: np.ndarray
    audio_rank: np.ndarray
    n_candidates: np.ndarray
    n_frames: int

    def __len__(self) -> int:
        return int(self.segments.shape[0])

    @property
    def rank(self) -> np.ndarray:
        """Rank sums ``pose_rank + audio_rank``, int64 (S,)."""
        return self.pose_rank + self.audio_rank

    def frame_map(self) -> np.ndarray:
        """Database frame copied to each output frame.

        Returns
        -------
        ndarray [shape=(T,)], int64
            ``out[t]`` is the global database frame placed at output frame ``t``.
        """
        return window_frame_map(self.frames, self.out_frames, self.lengths, self.n_frames)

    def step(self, i: int) -> StepResult:
        """Step ``i`` as a :class:`StepResult`."""
        return StepResult(
            segment=int(self.segments[i]),
            start=int(self.starts[i]),
            frame=int(self.frames[i]),
            length=int(self.lengths[i]),
            pose_dist=float(self.pose_dist[i]),
            audio_dist=float(self.audio_dist[i]),
            pose_rank=int(self.pose_rank[i]),
            audio_rank=int(self.audio_rank[i]),
            rank=int(self.pose_rank[i] + self.audio_rank[i]),
            n_candidates=int(self.n_candidates[i]),
        )


def window_frame_map(frames, out_frames, lengths, n_frames: int) -> np.ndarray:
    """Database frame placed at each output frame, from windows copied back to back.

    Parameters
    ----------
    frames, out_frames, lengths : ndarray [shape=(S,)], int64
        First database frame, first output frame and length of each window.
    n_frames : int
        T, the output length (``out_frames[-1] + lengths[-1]``).

    Returns
    -------
    ndarray [shape=(T,)], int64
    """
    offsets = np.arange(n_frames, dtype=np.int64) - np.repeat(out_frames, lengths)
    return np.repeat(frames, lengths) + offsets


def _pose_f16(pose_f16, pose):
    if pose_f16 is None:
        return None
    if not isinstance(pose_f16, HalfPose):
        raise ParameterError(f"pose_f16: expected gesturedb.search.HalfPose(pose); got {_describe(pose_f16)}")
    if pose_f16.pose is not pose:
        raise ParameterError(
            "pose_f16: expected a HalfPose made from this pose array; got one made from another "
            f"array {pose_f16.pose.shape} (searches would compare against the wrong rows)")
    return pose_f16.data.view(np.uint16)


def _pose_proj(pose_proj, pose):
    if pose_proj is None:
        return None
    if not isinstance(pose_proj, PoseProjection):
        raise ParameterError(
            f"pose_proj: expected gesturedb.search.PoseProjection(pose); got {_describe(pose_proj)}")
    if pose_proj.pose is not pose:
        raise ParameterError(
            "pose_proj: expected a PoseProjection made from this pose array; got one made from another "
            f"array {pose_proj.pose.shape} (searches would compare against the wrong rows)")
    if not np.isfinite(pose_proj.max_norm):
        return None  # an infinite pose value: no usable bound, the exact scan
    blocks = pose_proj.blocks.view(np.uint16) if pose_proj.half else pose_proj.blocks
    return (blocks, pose_proj.basis, pose_proj.mean, float(pose_proj.max_norm))


# --------------------------------------------------------------------------
# instruction-set control


def kernels() -> list[str]:
    """Instruction sets this build and CPU can run, e.g. ``['scalar', 'avx2', 'avx512']``."""
    return list(_core().kernels())


def get_simd() -> str:
    """The instruction set searches use now (initially the widest available,
    or ``$GESTUREDB_SIMD``)."""
    return str(_core().get_simd())


def set_simd(name: str) -> None:
    """Use instruction set ``name`` ('scalar', 'avx2', 'avx512') from now on."""
    available = kernels()
    if name not in available:
        raise ParameterError(f"simd: expected one of {available} on this CPU; got {name!r}")
    _core().set_simd(name)


@contextmanager
def simd(name: str) -> Iterator[None]:
    """Context manager running the enclosed searches with instruction set ``name``."""
    before = get_simd()
    set_simd(name)
    try:
        yield
    finally:
        _core().set_simd(before)


# --------------------------------------------------------------------------
# validation


def _describe(a) -> str:
    if not isinstance(a, np.ndarray):
        return type(a).__name__
    layout = "" if a.flags.c_contiguous else " non-contiguous"
    return f"{a.dtype}{layout} {a.shape}"


def _check_database(pose, audio, seg_start, seg_len):
    if not (isinstance(pose, np.ndarray) and pose.dtype == np.float32 and pose.ndim == 2
            and pose.flags.c_contiguous):
        raise ParameterError(f"pose: expected float32 C-contiguous (F, Dp); got {_describe(pose)}")
    if not (isinstance(audio, np.ndarray) and audio.dtype == np.float32 and audio.ndim == 2
            and audio.flags.c_contiguous):
        raise ParameterError(f"audio: expected float32 C-contiguous (F, Da); got {_describe(audio)}")
    F = pose.shape[0]
    if audio.shape[0] != F:
        raise ParameterError(
            f"audio: expected {F} rows (one per pose frame); got {audio.shape[0]} rows {audio.shape}")
    if pose.shape[1] < 1 or audio.shape[1] < 1:
        raise ParameterError(
            f"pose/audio: expected at least one feature column; got pose {pose.shape}, audio {audio.shape}")
    seg_start = _int_vector(seg_start, "seg_start")
    seg_len = _int_vector(seg_len, "seg_len")
    if seg_start.shape != seg_len.shape:
        raise ParameterError(
            f"seg_len: expected {seg_start.shape[0]} entries like seg_start; got {seg_len.shape[0]}")
    if seg_start.shape[0] < 1:
        raise ParameterError("seg_start: expected at least one segment; got 0")
    bad = np.flatnonzero(seg_len < 0)
    if bad.size:
        m = int(bad[0])
        raise ParameterError(f"seg_len: expected >= 0; got {int(seg_len[m])} at segment {m}")
    bad = np.flatnonzero(seg_start < 0)
    if bad.size:
        m = int(bad[0])
        raise ParameterError(f"seg_start: expected >= 0; got {int(seg_start[m])} at segment {m}")
    bad = np.flatnonzero(seg_start > F - seg_len)  # no overflow: both within int64 range
    if bad.size:
        m = int(bad[0])
        raise ParameterError(
            f"segment {m}: frames [{int(seg_start[m])}, {int(seg_start[m] + seg_len[m])}) "
            f"reach beyond the database (F = {F} frames)")
    return seg_start, seg_len


def _int_vector(a, name) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 1 or not (np.issubdtype(arr.dtype, np.integer) and arr.dtype != np.bool_):
        raise ParameterError(f"{name}: expected 1-d integer array (M,); got {_describe(arr)}")
    # segment tables are small (M values): converting them is cheap and harmless
    return np.ascontiguousarray(arr, dtype=np.int64)


def _float_array(a, name, shape_text, ndim) -> np.ndarray:
    """Small query-side arrays may be converted to float32 (they are not the database)."""
    try:
        arr = np.asarray(a)
    except Exception as exc:  # e.g. ragged lists
        raise ParameterError(f"{name}: expected {shape_text} float array; got {type(a).__name__} ({exc})") from None
    if arr.ndim != ndim or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)) \
            or arr.dtype == np.bool_:
        raise ParameterError(f"{name}: expected {shape_text} float array; got {_describe(arr)}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.isfinite(arr).all():
        idx = np.argwhere(~np.isfinite(arr))[0]
        raise ParameterError(f"{name}: expected finite values; got {arr[tuple(idx)]} at index {tuple(int(i) for i in idx)}")
    return arr


def _query(query_audio, Da, name) -> np.ndarray:
    q = _float_array(query_audio, name, f"(T, {Da})", 2)
    if q.shape[1] != Da:
        raise ParameterError(
            f"{name}: expected {Da} audio features per frame like the database; got shape {q.shape}")
    if q.shape[0] < 1:
        raise ParameterError(f"{name}: expected at least one frame (T >= 1); got shape {q.shape}")
    return q


def _pose_vector(p, Dp, name) -> np.ndarray:
    v = _float_array(p, name, f"({Dp},)", 1)
    if v.shape[0] != Dp:
        raise ParameterError(f"{name}: expected {Dp} pose features like the database; got shape {v.shape}")
    return v


def _positive_int(v, name) -> int:
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise ParameterError(f"{name}: expected an integer >= 1; got {v!r}")
    if v < 1:
        raise ParameterError(f"{name}: expected an integer >= 1; got {int(v)}")
    return int(v)


def _preselect(v) -> str:
    if v not in PRESELECT:
        raise ParameterError(f"preselect: expected 'pose' or 'audio'; got {v!r}")
    return v


def _threads(v) -> int:
    if v is None:
        return 0
    return _positive_int(v, "threads")


def _allowed(allowed, F, n_steps=None):
    """None, one bitset (W,) or, when n_steps is given, a per-step schedule (n_steps, W)."""
    if allowed is None:
        return None
    W = (F + 63) // 64
    if not isinstance(allowed, np.ndarray) or allowed.dtype != np.uint64:
        raise ParameterError(
            f"allowed: expected uint64 bitset ({W},) (ceil(F/64) words for F = {F} frames)"
            + (f" or ({n_steps}, {W}) one per step" if n_steps is not None else "")
            + f"; got {_describe(allowed)}")
    if allowed.ndim == 1 and allowed.shape[0] == W:
        return np.ascontiguousarray(allowed)
    if n_steps is not None and allowed.ndim == 2:
        if allowed.shape[1] != W:
            raise ParameterError(
                f"allowed: expected {W} uint64 words per bitset (F = {F} frames); got shape {allowed.shape}")
        if allowed.shape[0] != n_steps:
            raise ParameterError(
                f"allowed: expected {n_steps} rows (one bitset per step); got {allowed.shape[0]} rows "
                f"{allowed.shape}")
        return np.ascontiguousarray(allowed)
    raise ParameterError(
        f"allowed: expected uint64 bitset ({W},)"
        + (f" or ({n_steps}, {W}) one per step" if n_steps is not None else "")
        + f" for F = {F} frames; got shape {allowed.shape}")


def _exclude(exclude, M, Q=None):
    if exclude is None:
        return None
    if not isinstance(exclude, np.ndarray) or exclude.dtype != np.bool_:
        raise ParameterError(f"exclude: expected bool array ({M},); got {_describe(exclude)}")
    if exclude.shape == (M,) or (Q is not None and exclude.shape == (Q, M)):
        return np.ascontiguousarray(exclude)
    expected = f"({M},)" + (f" or ({Q}, {M})" if Q is not None else "")
    raise ParameterError(f"exclude: expected bool array {expected}; got shape {exclude.shape}")


def _no_candidate_error(step, t, n, seg_len, exclude, allowed_row, query=None):
    """SearchError explaining why step `step` had no candidate (cheap: runs only on failure)."""
    M = seg_len.shape[0]
    long_enough = seg_len - n >= 1
    reasons = [f"{int((~long_enough).sum())} of {M} segments are too short for a window of "
               f"{n} frames (need seg_len >= {n + 1})"]
    if exclude is not None:
        reasons.append(f"{int((exclude & long_enough).sum())} are excluded")
    if allowed_row is not None:
        reasons.append("the rest have no window whose first and last frame are set in `allowed`")
    where = f"query {query}, " if query is not None else ""
    err = SearchError(
        f"search {where}step {step} (output frame t={t}): no candidate window left: "
        + "; ".join(reasons))
    err.step = step
    err.t = t
    err.query = query
    return err


# --------------------------------------------------------------------------
# search


def rank_sum_step(pose, audio, seg_start, seg_len, prev_pose, query_audio, *, k=1,
                  preselect="pose", allowed=None, exclude=None, threads=None,
                  pose_f16=None, pose_proj=None) -> StepResult:
    """One rank-sum step: choose the next window of database frames.

    Parameters
    ----------
    pose : ndarray [shape=(F, Dp)], float32, C-contiguous
        Pose feature of every database frame.
    audio : ndarray [shape=(F, Da)], float32, C-contiguous
        Audio feature of every database frame.
    seg_start, seg_len : ndarray [shape=(M,)], int64
        First global frame and length (frames) of every segment.
    prev_pose : ndarray [shape=(Dp,)]
        Pose feature of the last output frame (or the initial pose).
    query_audio : ndarray [shape=(n, Da)]
        The query's audio features for this window; ``n`` is the window length.
    k : int
        Choose the k-th best (1-based); the last one if fewer remain.
    preselect : {"pose", "audio"}
        Distance that picks one candidate per segment.
    allowed : ndarray [shape=(ceil(F/64),)], uint64, optional
        Packed bitset of allowed frames; a window needs its first and last frame set.
    exclude : ndarray [shape=(M,)], bool, optional
        Segments to leave out.
    threads : int, optional
        Worker threads (default: the CPUs this process may use, ``_core.default_threads()``:
        its affinity mask bounded by the cgroup CPU quota).
    pose_f16 : HalfPose, optional
        ``HalfPose(pose)``: pose pre-selection reads half the bytes; same results.
    pose_proj : PoseProjection, optional
        ``PoseProjection(pose)``: pose pre-selection reads a quarter of the
        bytes; same results. Takes precedence over ``pose_f16``.

    Returns
    -------
    StepResult

    Raises
    ------
    ParameterError
        On any malformed argument.
    SearchError
        When no segment has an allowed candidate (attributes ``step = 0``, ``t = 0``).
    """
    seg_start, seg_len = _check_database(pose, audio, seg_start, seg_len)
    prev = _pose_vector(prev_pose, pose.shape[1], "prev_pose")
    q = _query(query_audio, audio.shape[1], "query_audio")
    k = _positive_int(k, "k")
    preselect = _preselect(preselect)
    allowed = _allowed(allowed, pose.shape[0])
    exclude = _exclude(exclude, seg_start.shape[0])
    half = _pose_f16(pose_f16, pose)
    proj = _pose_proj(pose_proj, pose)
    r = _core().step(pose, audio, seg_start, seg_len, prev, q, k, preselect, allowed, exclude,
                     _threads(threads), half, proj)
    if not r["found"]:
        raise _no_candidate_error(0, 0, q.shape[0], seg_len, exclude, allowed)
    return StepResult(
        segment=r["segment"], start=r["start"], frame=r["frame"], length=r["length"],
        pose_dist=r["pose_dist"], audio_dist=r["audio_dist"], pose_rank=r["pose_rank"],
        audio_rank=r["audio_rank"], rank=r["pose_rank"] + r["audio_rank"],
        n_candidates=r["n_candidates"])


def _result(d, T, sl=slice(None)) -> SearchResult:
    return SearchResult(
        segments=d["segments"][sl], starts=d["starts"][sl], frames=d["frames"][sl],
        lengths=d["lengths"][sl], out_frames=d["out_frames"][sl], pose_dist=d["pose_dist"][sl],
        audio_dist=d["audio_dist"][sl], pose_rank=d["pose_rank"][sl],
        audio_rank=d["audio_rank"][sl], n_candidates=d["n_candidates"][sl], n_frames=T)


def rank_sum_search(pose, audio, seg_start, seg_len, query_audio, init_pose, *, step=STEP_FRAMES, k=1,
                    preselect="pose", allowed=None, exclude=None, threads=None,
                    pose_f16=None, pose_proj=None) -> SearchResult:
    """Synthesize a sequence of database windows for a query's audio.

    Steps run at output frames ``t = 0, step, 2*step, ...``; each copies
    ``n = min(step, T - t)`` frames, so the last window may be shorter. The first
    step compares entry poses with ``init_pose``, every later step with the
    last frame the previous step copied.

    Parameters
    ----------
    pose, audio, seg_start, seg_len
        The database, as in :func:`rank_sum_step`.
    query_audio : ndarray [shape=(T, Da)]
        Audio features of the query, same extractor as the database.
    init_pose : ndarray [shape=(Dp,)]
        Previous pose for the first step (e.g. a random database frame or the mean pose).
    step : int
        Window length N in frames (paper: 8).
    k, preselect, exclude, threads, pose_f16
        As in :func:`rank_sum_step`.
    allowed : ndarray, uint64, optional
        One bitset ``(ceil(F/64),)`` for the whole search, or a control schedule
        ``(S, ceil(F/64))`` with one bitset per step, ``S = ceil(T / step)``.

    Returns
    -------
    SearchResult

    Raises
    ------
    ParameterError
        On any malformed argument.
    SearchError
        When a step has no candidate; attributes ``step`` (index) and ``t``
        (its output frame).
    """
    seg_start, seg_len = _check_database(pose, audio, seg_start, seg_len)
    q = _query(query_audio, audio.shape[1], "query_audio")
    init = _pose_vector(init_pose, pose.shape[1], "init_pose")
    N = _positive_int(step, "step")
    k = _positive_int(k, "k")
    preselect = _preselect(preselect)
    T = q.shape[0]
    S = -(-T // N)
    allowed = _allowed(allowed, pose.shape[0], S)
    exclude = _exclude(exclude, seg_start.shape[0])
    half = _pose_f16(pose_f16, pose)
    proj = _pose_proj(pose_proj, pose)
    d, failed = _core().search(pose, audio, seg_start, seg_len, q, init, N, k, preselect, allowed,
                               exclude, _threads(threads), half, proj)
    if failed >= 0:
        t = failed * N
        row = None if allowed is None else (allowed[failed] if allowed.ndim == 2 else allowed)
        raise _no_candidate_error(failed, t, min(N, T - t), seg_len, exclude, row)
    return _result(d, T)


def rank_sum_search_batch(pose, audio, seg_start, seg_len, queries: Sequence, init_poses, *,
                          step=STEP_FRAMES, k=1, preselect="pose", allowed=None, exclude=None,
                          threads=None, method="auto", pose_f16=None,
                          pose_proj=None, query_allowed=None) -> list[SearchResult]:
    """Run many independent searches in one call.

    Each result equals what :func:`rank_sum_search` returns for that query
    alone (same instruction set), whatever the method.

    With ``method="blocked"`` (the default from :func:`blocked_min_queries`
    queries on AVX2 / AVX-512: 3 a thread) blocks of up to 256 queries advance step by step together: each
    candidate row of the database is read once per block and step, an
    approximate distance to every query of the block comes from one blocked
    dot product (GEMM-like), and only the candidates whose rigorous error
    bound lets them still be a segment's minimum are recomputed with the exact
    kernels. ``method="per_query"`` runs the single-query search for each query.
    Blocks (or queries) run in parallel on ``threads`` threads.

    Parameters
    ----------
    pose, audio, seg_start, seg_len
        The database, as in :func:`rank_sum_step`.
    queries : sequence of ndarray [shape=(T_i, Da)]
        Audio features of each query (lengths may differ).
    init_poses : ndarray [shape=(Q, Dp)]
        Initial previous pose of each query.
    step : int
        Window length N in frames.
    k : int or sequence of int [shape=(Q,)]
        Rank of the choice, shared or per query.
    preselect : {"pose", "audio"}
    allowed : ndarray, uint64, optional
        One bitset ``(ceil(F/64),)`` for all queries, or a schedule
        ``(S, ceil(F/64))`` when every query has the same number of steps S.
    exclude : ndarray, bool, optional
        ``(M,)`` for all queries or ``(Q, M)`` per query (e.g. each query's own
        segment when the queries are the database's audio).
    query_allowed : ndarray [shape=(Q, ceil(F/64))], uint64, optional
        Instead of ``allowed``: each query's own bitset, for all its steps (clients with
        different controls in one batch). Queries with equal rows share the blocked
        filter's passes; per segment, queries whose bitsets allow the same candidates of
        it share one.
    threads : int, optional
        Worker threads (default: the CPUs this process may use, ``_core.default_threads()``:
        its affinity mask bounded by the cgroup CPU quota).
    method : {"auto", "blocked", "per_query"}
        Evaluation strategy (results are identical).
    pose_f16 : HalfPose, optional
        Used by the single-query steps (``per_query``, and the partial last
        windows of the blocked method); same results.
    pose_proj : PoseProjection, optional
        Pose pre-selection filters through the projection (24 columns per
        frame instead of 96) in every method: the blocked dot product then
        runs over the projected columns, with the projection's bound widened
        by the blocked form's rounding; same results. Worth it when its
        ``keep_fraction`` is small (real pose features).

    Returns
    -------
    list of SearchResult
        One per query, in order.

    Raises
    ------
    ParameterError
        On any malformed argument.
    SearchError
        When a step of some query has no candidate: the first such query is
        reported (attributes ``query``, ``step``, ``t``).
    """
    seg_start, seg_len = _check_database(pose, audio, seg_start, seg_len)
    if isinstance(queries, np.ndarray) or not isinstance(queries, Sequence):
        raise ParameterError(
            f"queries: expected a list of (T_i, {audio.shape[1]}) arrays; got {_describe(queries)}")
    Q = len(queries)
    Da, Dp, M = audio.shape[1], pose.shape[1], seg_start.shape[0]
    qs = [_query(q, Da, f"queries[{i}]") for i, q in enumerate(queries)]
    init = _float_array(init_poses, "init_poses", f"({Q}, {Dp})", 2)
    if init.shape != (Q, Dp):
        raise ParameterError(f"init_poses: expected ({Q}, {Dp}) (one pose per query); got {init.shape}")
    N = _positive_int(step, "step")
    if isinstance(k, numbers.Integral) and not isinstance(k, bool):
        ks = np.full(Q, _positive_int(k, "k"), dtype=np.int64)
    else:
        ks = np.asarray(k)
        if ks.shape != (Q,) or not np.issubdtype(ks.dtype, np.integer):
            raise ParameterError(f"k: expected an integer >= 1 or ({Q},) integers; got {_describe(ks)}")
        if Q and ks.min() < 1:
            i = int(np.argmin(ks))
            raise ParameterError(f"k: expected >= 1; got {int(ks[i])} for query {i}")
        ks = np.ascontiguousarray(ks, dtype=np.int64)
    preselect = _preselect(preselect)
    steps = [-(-q.shape[0] // N) for q in qs]
    if allowed is not None and isinstance(allowed, np.ndarray) and allowed.ndim == 2:
        if len(set(steps)) > 1:
            raise ParameterError(
                "allowed: a per-step schedule needs every query to have the same number of steps; "
                f"got {min(steps)} to {max(steps)} steps")
        allowed = _allowed(allowed, pose.shape[0], steps[0] if steps else 0)
    else:
        allowed = _allowed(allowed, pose.shape[0])
    exclude = _exclude(exclude, M, Q)
    if query_allowed is not None:
        W = (pose.shape[0] + 63) // 64
        if allowed is not None:
            raise ParameterError("allowed, query_allowed: expected one of them (a bitset or schedule for every "
                                 "query, or a bitset per query); got both")
        if (not isinstance(query_allowed, np.ndarray) or query_allowed.dtype != np.uint64
                or query_allowed.shape != (Q, W)):
            raise ParameterError(f"query_allowed: expected uint64 bitsets ({Q}, {W}) (one per query, F = "
                                 f"{pose.shape[0]} frames); got {_describe(query_allowed)}")
        query_allowed = np.ascontiguousarray(query_allowed)
    if method not in ("auto", "blocked", "per_query"):
        raise ParameterError(f"method: expected 'auto', 'blocked' or 'per_query'; got {method!r}")
    if Q == 0:
        return []
    half = _pose_f16(pose_f16, pose)
    proj = _pose_proj(pose_proj, pose)
    d, offsets, failed = _core().search_batch(pose, audio, seg_start, seg_len, qs, init, N, ks,
                                              preselect, allowed, exclude, _threads(threads), method,
                                              half, proj, query_allowed)
    bad = np.flatnonzero(failed >= 0)
    if bad.size:
        i = int(bad[0])
        s = int(failed[i])
        t = s * N
        row = query_allowed[i] if query_allowed is not None else (
            None if allowed is None else (allowed[s] if allowed.ndim == 2 else allowed))
        ex = None if exclude is None else (exclude[i] if exclude.ndim == 2 else exclude)
        err = _no_candidate_error(s, t, min(N, qs[i].shape[0] - t), seg_len, ex, row, query=i)
        if bad.size > 1:
            err.args = (err.args[0] + f" ({bad.size} of {Q} queries failed)",)
        raise err
    return [_result(d, qs[i].shape[0], slice(int(offsets[i]), int(offsets[i + 1]))) for i in range(Q)]
