"""Synthesis by motion matching (Habibie et al. 2022, Sec. 3.1) over an open database.

:class:`Searcher` is the convenient face over :mod:`gesturedb.search`: it turns
speech into query features with the database's own extractor and
standardisation, picks the initial pose (mean pose or a seeded random frame),
turns control schedules and keyword sub-databases into per-step bitsets, runs
the rank-sum search and assembles the chosen windows into a :class:`Motion`.

The first step's previous pose is by default a database frame drawn with
``seed`` (:data:`DEFAULT_INIT`), as the paper initialises the k-NN "in all
experiments" (Sec. 4) and as the refiner's training paths start; ``init="mean"``
(the paper's other option) starts from the mean pose.

Window boundaries, placement and foot contacts are the shared assembly's
(:mod:`gesturedb.synth.assemble`): each window continues the output's root from
where it is, and the step in position, velocity and acceleration at each seam is
inertialized (an offset that decays to zero over ``seam_decay_s``, one step's
0.53 s by default; :mod:`gesturedb.synth.seams`); ``seam_decay_s=0`` copies the windows
back to back as in the paper.

:class:`Stream` is the same search as the speech arrives (``Searcher.stream``, also named
``gesturedb.synth.stream.Stream``; its latency is explained there); ``Searcher.synthesize``
is a stream fed the whole file, so the two give the same frames.
"""
from __future__ import annotations

import math
import threading

import numpy as np

from gesturedb.control import candidate_counts, compile_mask, full_mask, mask_and, suggest_percentiles
from gesturedb.control.schedule import _schedule_items
from gesturedb.db import keywords as kw
from gesturedb.db.shards import ShardedSearch
from gesturedb.errors import ParameterError, SearchError
from gesturedb.features.audio import AUDIO_WINDOW_S, AudioFeatureStream, audio_deltas, n_frames_for_duration
from gesturedb.io.transcripts import Words, normalize_word
from gesturedb.motion import Motion
from gesturedb.search import HalfPose, PoseProjection, _no_candidate_error, rank_sum_search
from gesturedb.synth import inputs
from gesturedb.synth.assemble import (
    PieceAssembler,
    assemble_frames,
    floor_height,
    typical_accelerations,
    window_piece,
    window_pieces,
)
from gesturedb.synth.background import Awaited, Background
from gesturedb.synth.inputs import (
    check_frames,
    speech_samples,  # noqa: F401  (its old home; every method's now)
)
from gesturedb.synth.options import (  # noqa: F401  (re-exported from their old home)
    DEFAULT_INIT,
    INIT_CHOICES,
    STEP_S,
    SearchOptions,
    default_step,
)
from gesturedb.synth.protocol import EvalSystem, Method
from gesturedb.synth.repeats import Overlaps, check_guard_s, clear_frames, repeat_stats
from gesturedb.synth.result import StreamChunk, SynthResult, chunk_motion
from gesturedb.synth.seams import SEAM_DECAY_S, check_decay_s
from gesturedb.synth.stepquery import StepQuery  # noqa: F401  (re-exported from its old home)


class Searcher:
    """Search an open database for new speech (the ``knn`` method of :mod:`gesturedb.synth.methods`).

    Parameters
    ----------
    db : gesturedb.db.database.Database
    segments : {"chunks", "clips"} or str
        Which segmentation to search (the paper uses 64-frame chunks).
    half_precision : bool
        Stream a half-precision copy of the pose features in pose steps
        (:class:`gesturedb.search.HalfPose`): identical results, about 30%
        faster searches on large databases, for 0.4 s and 2 bytes per value
        spent once (616k frames). Worth it when one Searcher runs many syntheses.
    projection : bool
        Pose steps stream a 24-column projection of the pose features in
        binary16 (:class:`gesturedb.search.PoseProjection` with ``half=True``,
        built in a background thread after the first pose search; the steps
        scan exactly until it is ready): identical results, an eighth of the
        bytes per step. On by
        default (skipped when it would keep a quarter of the candidates or
        more); takes precedence over ``half_precision``.
    scheduler : distributed.Client, optional
        Search over ``parts`` shards resident on this Dask cluster's workers
        (:class:`gesturedb.db.shards.ShardedSearch`, built at the first
        search): exactly the same output as the search in this process. The
        name every Dask entry point takes (``build``, ``ShardedSearch``, the
        refiner's training data); ``client=`` is the older spelling, still
        accepted.
    parts : int
        Number of shards with ``scheduler``. A database opened from an index file
        (``gesturedb shard``) is searched over its own shard files instead, each
        read by a worker (:meth:`ShardedSearch.from_shard_files`).
    """

    def __init__(self, db, *, segments: str = "chunks", half_precision: bool = False,
                 projection: bool = True, scheduler=None, parts: int = 2, client=None):
        if client is not None and scheduler is not None:
            raise ParameterError("Searcher: expected scheduler= or its older spelling client=, not both")
        self.db = db
        self._client, self._parts, self._sharded = scheduler if scheduler is not None else client, parts, None
        self._projection = bool(projection)
        # the projection and the seams' accelerations, each built once in a Background thread while
        # the first steps run without them (the lock: once, also when a server's streams start together)
        self._lock = threading.Lock()
        self._proj_job = None
        self._accel_job = None
        self._half = HalfPose(db.pose_features) if half_precision else None
        if segments == "chunks":
            seg = db.chunks
        elif segments == "clips":
            seg = db.clips
        else:
            raise ParameterError(f"segments: expected 'chunks' or 'clips', got {segments!r}")
        self.segments_kind = segments
        self.seg_start = np.ascontiguousarray(seg.start, dtype=np.int64)
        self.seg_len = np.ascontiguousarray(seg.length, dtype=np.int64)
        self.seg_recording = np.asarray(seg.recording)

    def pose_projection(self, *, wait: bool = True):
        """The :class:`gesturedb.search.PoseProjection` of the database's pose
        features, built once; None when ``projection=False`` or when it would
        keep a quarter of the candidates or more (pose features without the
        structure of motion: the filter would only add work).

        The build (a pass over every pose row and a covariance: 4-7 s at paper scale,
        616k frames) runs in a background thread, started by the first call. ``wait=False``
        returns None until it is done instead of waiting: the pose steps search without the
        filter meanwhile, which gives the same results (it is an exact filter), so a stream's
        first frame does not wait for it.
        """
        if not self._projection:
            return None
        with self._lock:
            if self._proj_job is None:
                self._proj_job = Background(self._build_projection, "gesturedb-pose-projection")
        if not (wait or self._proj_job.ready()):
            return None
        proj = self._proj_job.result()
        if proj is None:
            self._projection = False
        return proj

    def _build_projection(self):
        accel = self._accel_job
        if accel is not None:
            # one background job at a time, in the order they are needed: the accelerations (a stream's
            # first seam waits for them) before the projection (no step waits for it)
            accel.wait()
        # binary16 rows: half the stream of float32 rows for a few more exact checks
        proj = PoseProjection(self.db.pose_features, half=True)
        return proj if proj.keep_fraction < 0.25 else None

    def seam_accelerations(self):
        """The database's typical accelerations, which a seam's decay is scaled by
        (:func:`gesturedb.synth.assemble.typical_accelerations`: (J,) rad/s^2 and m/s^2), as
        a pair that is computed in a background thread (started by the first call) and waited
        for where it is first indexed: a stream's first seam, at its second step, not its first
        frame (about 1.2 s at paper scale, from 32k sampled frames; the same bits either way)."""
        with self._lock:
            if self._accel_job is None:
                self._accel_job = Background(lambda: typical_accelerations(self.db), "gesturedb-seam-accelerations")
        return Awaited(self._accel_job)

    # -- inputs ---------------------------------------------------------------
    def query_features(self, samples: np.ndarray, sr: int) -> np.ndarray:
        """Audio features of new speech, standardised like the database's
        (:func:`gesturedb.synth.inputs.query_features`), (T, Da) float32."""
        return inputs.query_features(self.db, samples, sr)

    def initial_pose(self, init: str = DEFAULT_INIT, *, seed: int | None = 0) -> np.ndarray:
        """The first step's previous pose (Sec. 3.1), (Dp,) float32: a random database frame drawn
        with ``seed`` (None: unseeded) or the database's mean pose feature."""
        # rows and chunks, not the whole matrix: a client searching over shards
        # never loads the pose features
        if init == "mean":
            return self.db.frame_mean("pose_features").astype(np.float32)
        if init == "random":
            rng = np.random.default_rng(seed)
            return np.array(self.db.rows("pose_features", [int(rng.integers(self.db.n_frames))])[0], dtype=np.float32)
        raise ParameterError(f"init: expected {' or '.join(map(repr, INIT_CHOICES))}, got {init!r}")

    def exclude_recordings(self, names, speaker: str | None = None) -> np.ndarray | None:
        """bool per segment: True for segments of the named recordings (e.g. a query's own recording)
        and, with ``speaker``, of every other speaker's (:func:`gesturedb.synth.inputs.excluded`)."""
        return inputs.excluded(self.db, self.seg_recording, names, speaker)

    # -- the search -----------------------------------------------------------
    def synthesize(self, audio, *, sr: int | None = None, transcript=None, refiner=None,
                   options: SearchOptions | None = None, **changes) -> SynthResult:
        """Synthesize gestures for speech.

        Parameters
        ----------
        audio : path or ndarray [shape=(n,)]
            A WAV file, or mono samples with ``sr``; at least
            :data:`gesturedb.synth.inputs.MIN_SPEECH_S` long.
        transcript : path, Words or None
            Word timings of the speech; needed for keyword sub-databases.
        refiner : object with ``refine(motion, audio)``, optional
            Applied to the assembled motion in one pass, e.g. a trained
            :class:`gesturedb.refiner.train.Refiner` (``audio`` is the query's
            standardised features and their deltas, (T, 28)). Any object with
            that method works, so synthesis does not depend on the refiner stage.
        options : SearchOptions, optional
            The search's options (:class:`gesturedb.synth.options.SearchOptions`:
            ``k``, ``preselect``, ``init``, ``seed``, ``step``, ``seam_decay_s``,
            ``smooth``, ``control``, ``keywords``, ``exclude``, ``speaker``,
            ``repeat_guard_s``; their defaults when None).
        **changes
            Any of those fields as keywords, over ``options``
            (``synthesize(wav, seed=3, control="left_wrist_height > p85")``).
            Steps the repeat guard would leave without a candidate run without it
            (counted in ``repeats["guard_relaxed"]``).

        Returns
        -------
        SynthResult
            ``steps[i]`` holds: ``step``, ``out_start``/``out_end`` (output frames),
            ``time_s``, ``recording``, ``source_start_s``/``source_end_s``, ``segment``,
            ``segment_start``, ``db_frame``, ``pose_dist``, ``audio_dist``, ``pose_rank``,
            ``audio_rank``, ``control`` and ``keyword`` (None when unconstrained),
            ``repeat_of`` (the latest earlier step whose window overlaps this one's,
            or None) and ``guard_relaxed``; ``repeats`` summarises them
            (:func:`gesturedb.synth.repeats.repeat_stats`).
        """
        opts = SearchOptions.of(options, **changes)
        db = self.db
        samples, sr, audio_path = speech_samples(db, audio, sr)
        self._check_options(opts)
        transcript = inputs.read_words(transcript, samples.shape[0] / sr, audio=audio_path)
        T = inputs.check_speech(samples.shape[0], sr, db.fps, audio=audio_path)
        self._check_window(min(opts.step_at(db.fps), T))
        if opts.control:
            # a schedule item that no step's centre falls in is an error before any search (the stream,
            # which does not know the length, takes each step's control as it comes)
            step = opts.step_at(db.fps)
            self._step_masks(opts.control, None, False, n_steps=-(-T // step), step=step, T=T)
        stream = Stream(db, opts.replace(smooth=False), sample_rate=sr, searcher=self, _whole=True)
        if transcript is not None and opts.keywords:
            stream.push_words(transcript)
        stream.push(samples)
        stream.finish()
        control, keywords, guard_s = opts.control, opts.keywords, stream.guard_s
        options = dict(k=opts.k, preselect=opts.preselect, init=opts.init, seed=opts.seed, step=stream.step,
                       seam_decay_s=stream.seam_decay_s, smooth=opts.smooth,
                       control=control if isinstance(control, (str, type(None))) else str(control),
                       keywords=keywords if isinstance(keywords, bool) else list(keywords),
                       segments=self.segments_kind, database=db.path,
                       refiner=None if refiner is None else str(getattr(refiner, "path", None) or type(refiner).__name__),
                       speaker=opts.speaker, repeat_guard_s=guard_s)
        res = stream.result(audio_path=audio_path, options=options)
        if opts.smooth:  # the smoothing needs frames on both sides: the whole motion again, smoothed
            res.motion = self.assemble(res.source_frames, np.r_[0, res.boundaries], seam_decay_s=stream.seam_decay_s,
                                       smooth=True)
        if refiner is not None:
            query = stream.query
            res.motion = refiner.refine(res.motion, np.concatenate([query, audio_deltas(query)], axis=1))
        return res

    def stream(self, options: SearchOptions | None = None, *, sample_rate: int, n_samples: int | None = None) -> Stream:
        """A live synthesis over this searcher (:class:`gesturedb.synth.stream.Stream`)."""
        return Stream(self.db, options, sample_rate=sample_rate, searcher=self, n_samples=n_samples)

    # -- the pieces a synthesis is made of ---------------------------------------
    def _check_options(self, opts: SearchOptions) -> tuple[int, float, float]:
        """The step (frames), seam decay (s) and repeat guard (s) of valid options; ParameterError otherwise."""
        k, seed = opts.k, opts.seed
        step = opts.step_at(self.db.fps)
        if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 1:
            raise ParameterError(f"step: expected a positive number of frames, got {step!r}")
        decay_s = check_decay_s(opts.seam_decay_s)
        n_seg = len(self.seg_start)
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= max(n_seg, 1):
            raise ParameterError(f"k: expected an integer from 1 to the number of {self.segments_kind} of "
                                 f"{self.db.path} ({n_seg}), got {k!r}")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))
                                 or not 0 <= seed < 2**63):
            raise ParameterError(f"seed: expected an integer from 0 to 2**63-1, got {seed!r}")
        if opts.init not in INIT_CHOICES:
            raise ParameterError(f"init: expected {' or '.join(map(repr, INIT_CHOICES))}, got {opts.init!r}")
        return int(step), decay_s, check_guard_s(opts.repeat_guard_s)

    def _check_window(self, n: int) -> None:
        """A segment must hold a window of ``n`` frames and its entry frame."""
        longest = int(self.seg_len.max(initial=0))
        if longest < n + 1:
            raise ParameterError(f"database {self.db.path}: no {self.segments_kind} segment is long enough for a "
                                 f"window of {n} frames plus its entry frame (longest: {longest} frames)")

    def _step_search(self, *, step: int, k: int, preselect: str, exclude=None, speaker=None):
        """One search step ``(query (n, Da), prev (Dp,), allowed (1, W)) -> SearchResult`` over this database
        (the kernel, or the shards of the Dask client); ``.exclude`` is its bool per segment."""
        excl = self.exclude_recordings(exclude, speaker)
        db = self.db

        def search(q, prev, allowed_now):
            if self._client is not None:
                if self._sharded is None:
                    self._sharded = ShardedSearch.for_database(db, self.seg_start, self.seg_len,
                                                               scheduler=self._client, parts=self._parts)
                return self._sharded.search(q, prev, step=step, k=k, preselect=preselect,
                                            allowed=allowed_now, exclude=excl)
            proj = None
            if preselect == "pose":
                # not waiting: until the projection is built in the background the step scans exactly
                # (0.05 s at paper scale); its build starts after this search, so that a stream's
                # first step does not share the CPU with it
                proj = self.pose_projection(wait=False) if self._proj_job is not None else None
            res = rank_sum_search(
                db.pose_features, db.audio_features, self.seg_start, self.seg_len, q, prev,
                step=step, k=k, preselect=preselect, exclude=excl, pose_f16=self._half,
                allowed=None if allowed_now is None else np.ascontiguousarray(allowed_now),
                pose_proj=proj,
            )
            if preselect == "pose" and self._proj_job is None:
                self.pose_projection(wait=False)
            return res

        search.exclude = excl
        return search

    # -- masks ------------------------------------------------------------------
    def _step_masks(self, control, transcript, keywords, *, n_steps, step, T):
        """:func:`gesturedb.synth.inputs.step_masks` over this searcher's database."""
        return inputs.step_masks(self.db, control, transcript, keywords, n_steps=n_steps, step=step, T=T)

    def _explain(self, exc: SearchError, labels, *, keyword_bits, exclude, step, T) -> SearchError:
        """Name the step, its time and the control that emptied it, and suggest a percentile that works."""
        i = getattr(exc, "step", None)
        t = getattr(exc, "t", None)
        if i is None or labels is None or labels[i] is None:
            return exc
        ctl, kwd = labels[i]
        msg = f"step {i} (output frame {t}, t = {t / self.db.fps:.2f} s) has no candidate"
        if ctl:
            msg += f" under control {ctl!r}"
            n = min(step, T - i * step)
            # "has candidates" means a window whose first and last frames are both allowed
            # (and, on a keyword step, inside the keyword's sub-database)
            within = keyword_bits[i] if kwd else None

            def accept(words):
                w = words if within is None else mask_and(words, within)
                return candidate_counts(w, n_frames=self.db.n_frames, seg_start=self.seg_start,
                                              seg_len=self.seg_len, n=n, exclude=exclude).sum() > 0

            hints = suggest_percentiles(ctl, controls=self.db.control_datasets, named=self.db.mask_datasets, accept=accept)
            if hints:
                msg += "; " + "; ".join(str(h) for h in hints)
        if kwd:
            msg += f" in keyword sub-database {kwd!r}"
        err = SearchError(msg)
        err.step, err.t = i, t
        return err

    # -- assembly ---------------------------------------------------------------
    def assemble(self, source: np.ndarray, starts: np.ndarray, *, seam_decay_s: float = SEAM_DECAY_S,
                 smooth: bool = False):
        """Copy the chosen database frames into one Motion; see :func:`gesturedb.synth.assemble.assemble_frames`."""
        return assemble_frames(self.db, source, starts, seam_decay_s=seam_decay_s, smooth=smooth)


# ==================================================================== the live search
class Stream:
    """The k-NN synthesis of speech that arrives in chunks.

    ``Searcher.synthesize`` is a stream made with ``_whole=True``: every step as here, the frames
    assembled at :meth:`finish` (the kinematics of all frames at once: the same bits, faster).
    A server of many streams runs each step in its parts (:meth:`next_step`, a search of many
    streams' steps at once, :meth:`complete_step`; :mod:`gesturedb.synth.stepbatch`).

    Parameters
    ----------
    db : gesturedb.db.database.Database
    options : SearchOptions, optional
        As for :meth:`gesturedb.synth.Searcher.synthesize` (``smooth`` must be False);
        ``control`` is the starting control (a schedule's times are output seconds).
    sample_rate : int
        Rate of the samples pushed, Hz (any rate: the features are computed at it).
    searcher : gesturedb.synth.Searcher, optional
        The searcher to use (its segments, projection or Dask client); default ``Searcher(db)``.
        One searcher can serve many streams.
    n_samples : int >= 0, optional
        The speech's whole length in samples, when it is known before all of it has come (a file
        streamed): the last step, shorter where the speech ends within it, is then known ahead
        (:meth:`upcoming_step`) and a server pre-selects it like the others. Only that: the frames
        do not depend on it, and speech of another length ends as without it.
    """

    def __init__(self, db, options: SearchOptions | None = None, *, sample_rate: int, searcher=None,
                 n_samples: int | None = None, _whole: bool = False):
        self.db = db
        self.searcher = searcher if searcher is not None else Searcher(db)
        self.options = opts = SearchOptions.of(options)
        if opts.smooth:
            raise ParameterError("smooth: a stream cannot smooth (the filter needs the frames after each one); "
                                 "synthesize the whole file with smooth=True instead")
        self.step, self.seam_decay_s, self.guard_s = self.searcher._check_options(opts)
        if isinstance(sample_rate, bool) or not isinstance(sample_rate, (int, np.integer)) or sample_rate < 1:
            raise ParameterError(f"sample_rate: expected a positive int (Hz), got {sample_rate!r}")
        self.sample_rate = int(sample_rate)
        self.fps = float(db.fps)
        if n_samples is not None and (isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer))
                                      or n_samples < 0):
            raise ParameterError(f"n_samples: expected the speech's length as an int >= 0 or None, got {n_samples!r}")
        # the output frames of that much speech (as finish() will count them), None: unknown
        self._n_expected = None if n_samples is None else n_frames_for_duration(n_samples / self.sample_rate, self.fps)
        self._features = AudioFeatureStream(self.sample_rate, fps=db.fps, n_mfcc=int(db.config.get("n_mfcc", 13)))
        # the standardised features so far: rows [0, _n_query) of a buffer that doubles when full (a new
        # array at each feed copied all of them: a megabyte a step after 20 minutes)
        self._query_buf = np.zeros((256, db.audio_mean.shape[0]), dtype=np.float32)
        self._n_query = 0
        self._search = self.searcher._step_search(step=self.step, k=opts.k, preselect=opts.preselect,
                                                  exclude=opts.exclude, speaker=opts.speaker)
        self._excl = self._search.exclude
        self._prev = self.searcher.initial_pose(opts.init, seed=opts.seed)
        self._full = full_mask(db.n_frames)
        self._guard_frames = int(round(self.guard_s * db.fps))
        self._masks: dict = {}
        self._schedule = []
        self.set_control(opts.control)
        self._keywords = opts.keywords
        self._words: list[tuple[float, float, str]] = []
        self._asm = PieceAssembler(db.skeleton, db.fps, seam_decay_s=self.seam_decay_s,
                                   seam_accel=self.searcher.seam_accelerations() if self.seam_decay_s > 0 else None,
                                   floor_y=floor_height(db), batch=_whole)
        self._whole = _whole
        self._held: list[tuple] = []  # _whole: the windows (frames, output frame, previous frame), read at finish
        self._windows: list[tuple[int, int, int]] = []  # (output frame, first database frame, length) per step
        self._overlaps = Overlaps()
        self._steps: list[dict] = []
        self._relaxed: list[bool] = []
        self._source: list[np.ndarray] = []
        self._n_out = 0
        self._steps_out = 0
        self._rot, self._root = [], []  # every final frame, for result()
        self._pending = []  # (rotations, root) made final since the last chunk
        self._speech_over = False  # end_speech(): every feature is in, the last (partial) steps may run
        self._finished = False

    # -- what it waits for ---------------------------------------------------------
    @property
    def latency_s(self) -> float:
        """Algorithmic latency (s): a step's frames, the audio features' context and the feet's lag."""
        win = max(1, int(round(AUDIO_WINDOW_S * self.sample_rate)))
        n_fft = 1 << (win - 1).bit_length()
        return (self.step + self._asm.lag) / self.fps + (n_fft // 2) / self.sample_rate

    # -- inputs ------------------------------------------------------------------
    def set_control(self, expr_or_mask_name: str | None) -> None:
        """The control from the next step on: a mask expression or saved mask name (None: none).
        A schedule (``"0-12: high; 12-: slow"``, output seconds) is accepted too."""
        expr = expr_or_mask_name
        if expr is None or (isinstance(expr, str) and not expr.strip()):
            self._schedule = []
            return
        sched = [(0.0, None, expr)] if isinstance(expr, str) and ":" not in expr else expr
        items = [item for _, _, item in _schedule_items(sched)]
        for item in items:
            self._mask(item.expr)  # an unknown name or a bad expression fails now, not at the next step
        self._schedule = items

    def _mask(self, expr: str) -> np.ndarray:
        if expr not in self._masks:
            db = self.db
            self._masks[expr] = compile_mask(expr, controls=db.control_datasets, named=db.mask_datasets,
                                             n_frames=db.n_frames).words
        return self._masks[expr]

    def push_words(self, words) -> None:
        """Word timings of the speech, ``(start_s, end_s, text)`` each (or :class:`Words`), for keyword
        sub-databases: a step uses the words pushed before it runs."""
        if isinstance(words, Words):
            self._words += list(zip(words.start_s.tolist(), words.end_s.tolist(), words.text))
            return
        for w in words:
            if not isinstance(w, (tuple, list)) or len(w) != 3:
                raise ParameterError(f"words: expected (start_s, end_s, text) items, got {w!r}")
            self._words.append((float(w[0]), float(w[1]), normalize_word(str(w[2]))))

    def push(self, samples) -> StreamChunk:
        """Add speech samples (float32 mono in [-1, 1], any length); the frames that became final."""
        self.feed(samples)
        self._run_ready_steps()
        return self._chunk()

    # -- a step in three parts, for a server that searches many streams' steps at once ---------------
    # push() is feed(), then per ready step next_step() (prepare), search_step() (search) and
    # complete_step() (apply), then take_chunk(); gesturedb.synth.stepbatch runs the same prepare and
    # apply around one search call for many streams, so the two cannot drift.
    def feed(self, samples) -> None:
        """Add speech samples (float32 mono in [-1, 1], any length) without running the steps they make
        ready: :meth:`next_step` gives them one at a time."""
        if self._finished:
            raise ParameterError("Stream.push: the stream is finished; start a new one")
        if self._speech_over:
            raise ParameterError("Stream.push: the stream's speech has ended (end_speech); finish it and start a "
                                 "new one")
        self._add_features(self._features.push(samples))

    def next_step(self) -> StepQuery | None:
        """The next search step that the speech fed so far makes ready (all its audio features), prepared
        for the search; None while it waits for more speech (or once the stream is finished). After
        :meth:`end_speech` also the last steps, the final one shorter where the speech ends within it."""
        return None if self._finished else self._next_ready()

    def _next_ready(self) -> StepQuery | None:
        left = self._n_query - len(self._windows) * self.step
        if left >= self.step:
            return self._prepare_step(self.step)
        return self._prepare_step(left) if self._speech_over and left > 0 else None

    def end_speech(self) -> None:
        """The speech is over: its last features are computed, and :meth:`next_step` gives the last steps
        (a server searches them with other streams' steps); :meth:`finish` then gives the remaining frames.
        Calling :meth:`finish` directly does both."""
        if self._finished or self._speech_over:
            raise ParameterError("Stream.end_speech: the speech of this stream has already ended")
        self._last_features()
        check_frames(self._n_query, self.fps)  # too little speech is an error here already

    def _last_features(self) -> None:
        self._speech_over = True
        self._add_features(self._features.finish())

    def upcoming_step(self) -> StepQuery | None:
        """The next step as it would be prepared now, before its speech has come (``query`` without rows):
        with pre-selection ``"pose"`` its table but for the audio distances depends on nothing else, so a
        server pre-selects it while the speech arrives (:meth:`gesturedb.synth.stepbatch.StepBatch.speculate`)
        and checks it against :meth:`next_step`'s with :meth:`StepQuery.same_but_audio` (a control or words
        pushed in between make it stale). None once the stream is finished or with pre-selection ``"audio"``.
        A full step, but for the last one of a stream told its length (``n_samples``)."""
        if self._finished or self._speech_over or self.options.preselect != "pose":
            return None
        n = self.step
        if self._n_expected is not None:
            left = self._n_expected - len(self._windows) * self.step
            n = left if 0 < left < n else n  # past the length told (more speech came): full steps again
        return self._prepare_step(n, with_query=False)

    def search_step(self, sq: StepQuery):
        """``(res, relaxed)``: step ``sq`` searched alone, as :meth:`push` searches it (with the repeat
        guard, then without it when the guard leaves no candidate, ``relaxed`` True). ``res`` is a
        one-step :class:`gesturedb.search.SearchResult`. Raises the step's explained SearchError
        (naming the control that emptied it) when nothing is left."""
        return self._search_step(sq)

    def complete_step(self, sq: StepQuery, res, relaxed: bool) -> None:
        """Apply step ``sq``'s search result (``res``, ``relaxed`` as :meth:`search_step` returns them):
        its provenance, the next step's previous pose and its frames."""
        if sq.stream is not self or sq.i != len(self._windows):
            raise ParameterError(f"Stream.complete_step: expected step {len(self._windows)} of this stream; got "
                                 f"step {sq.i}" + ("" if sq.stream is self else " of another stream"))
        self._apply_step(sq, res, relaxed)

    def samples_before_step(self) -> int:
        """Samples to push in all (from the stream's start) before :meth:`next_step` can give the next
        step, a lower bound: the step's own audio (its last frame's features need its audio, and a
        little context after it). A caller that feeds audio in small pieces can hold them until then
        and feed them at once: the features are the same whatever the pieces, and fewer calls cost less."""
        return int(math.floor((len(self._windows) + 1) * self.step * self.sample_rate / self.fps))

    def take_chunk(self) -> StreamChunk:
        """The frames that the steps completed since the last chunk made final (what :meth:`push` returns)."""
        return self._chunk()

    def finish(self) -> StreamChunk:
        """The remaining frames: the speech is over (its last step may be shorter)."""
        if self._finished:
            raise ParameterError("Stream.finish: the stream is already finished")
        if not self._speech_over:
            self._last_features()
        self._finished = True
        check_frames(self._n_query, self.fps)
        self._run_ready_steps()  # the last steps, the final one shorter (a server has run them already)
        if self._held:
            for piece, (frames, t, _) in zip(window_pieces(self.db, self._held, seam_decay_s=self.seam_decay_s),
                                             self._held):
                self._pending.append(self._asm.add(piece, end=t + frames.shape[0]))
        return self._chunk(self._asm.finish())

    def _add_features(self, raw: np.ndarray) -> None:
        if raw.shape[0]:
            db = self.db
            q = ((raw.astype(np.float64) - db.audio_mean) / db.audio_std).astype(np.float32)
            n = self._n_query + q.shape[0]
            if n > self._query_buf.shape[0]:
                grown = np.zeros((2 * n, q.shape[1]), dtype=np.float32)
                grown[:self._n_query] = self.query
                self._query_buf = grown
            self._query_buf[self._n_query:n] = q
            self._n_query = n

    # -- one step ------------------------------------------------------------------
    def _step_rows(self, i: int, t: int, n: int):
        """The step's allowed bitset (None: unconstrained), its (control, keyword) label and keyword row."""
        ctl = None
        centre = t + n / 2.0  # in output frames, exact: the control active at the step's centre
        for item in self._schedule:  # sorted by start: a later item wins, as in schedule_bitsets
            a = round(item.start_s * self.fps, 9)
            b = np.inf if item.end_s is None else round(item.end_s * self.fps, 9)
            if a <= centre < b:
                ctl = item.expr
        row = None if ctl is None else self._mask(ctl)
        kwd, kw_row = None, None
        if self._keywords and self._words:
            # the words that can overlap this step (keyword_step_masks over the steps so far: row i is
            # that of the whole synthesis, which clips at the step's end only on its last step)
            near = [w for w in self._words if w[1] * self.fps >= t - 2]
            if near:
                words = Words([w[0] for w in near], [w[1] for w in near], [w[2] for w in near])
                res = kw.keyword_step_masks(self.db, words, n_steps=i + 1, step=self.step, n_out_frames=t + n,
                                            only=None if self._keywords is True else list(self._keywords),
                                            compact=True)
                if res is not None and res[1][i] is not None:
                    kwd, kw_row = res[1][i], np.asarray(res[0][i])
        if kw_row is not None:
            row = kw_row if row is None else row & kw_row
        label = (ctl, kwd) if (ctl is not None or kwd is not None) else None
        return row, label, kw_row

    def _run_ready_steps(self) -> None:
        """Search and apply every step the speech so far makes ready (:meth:`next_step`), each alone."""
        while (sq := self._next_ready()) is not None:
            self._apply_step(sq, *self._search_step(sq))

    def _prepare_step(self, n: int, *, with_query: bool = True) -> StepQuery:
        """Step ``len(windows)`` of ``n`` frames: its query rows (none without ``with_query``), previous
        pose and allowed rows."""
        i = len(self._windows)
        t = i * self.step
        if i == 0:
            self.searcher._check_window(n)
        row, label, kw_row = self._step_rows(i, t, n)
        allowed = self._full if row is None else np.ascontiguousarray(row)
        recent = []  # the windows within the repeat guard: the latest ones
        for t0, g, m in reversed(self._windows):
            if t - t0 >= self._guard_frames:
                break
            recent.append((g, g + m))
        recent.reverse()
        query = self.query[t:t + n] if with_query else self.query[:0]
        return StepQuery(stream=self, i=i, t=t, n=n, query=query, prev=self._prev,
                         row=None if row is None else allowed, allowed=allowed, recent=recent,
                         guarded=clear_frames(allowed, recent) if recent else None, label=label, kw_row=kw_row)

    def _search_step(self, sq: StepQuery):
        """``(res, relaxed)`` of one step searched alone: with the repeat guard, then without it."""
        res, relaxed = None, False
        i, t, n = sq.i, sq.t, sq.n
        try:
            if sq.guarded is not None:
                try:
                    res = self._search(sq.query, sq.prev, sq.guarded[None, :])
                except SearchError:
                    relaxed = True
            if res is None:
                try:
                    res = self._search(sq.query, sq.prev, sq.allowed[None, :])
                except SearchError:
                    raise _no_candidate_error(i, t, n, self.searcher.seg_len, self._excl, sq.row) from None
        except SearchError as exc:
            raise self.searcher._explain(exc, {i: sq.label}, keyword_bits={i: sq.kw_row}, exclude=self._excl,
                                         step=self.step, T=t + n) from None
        return res, relaxed

    def _apply_step(self, sq: StepQuery, res, relaxed: bool) -> None:
        """Step ``sq``'s chosen window into the stream: its provenance, the next previous pose, its frames."""
        i, t, n, label = sq.i, sq.t, sq.n, sq.label
        g = int(res.frames[0])
        db = self.db
        self._windows.append((t, g, n))
        self._relaxed.append(relaxed)
        self._prev = np.ascontiguousarray(db.rows("pose_features", [g + n - 1])[0], dtype=np.float32)
        frames = g + np.arange(n, dtype=np.int64)
        self._source.append(frames)
        # the segment's recording is its frames' (a segment never spans two): no read of the file per step
        rec = db.recordings[int(self.searcher.seg_recording[int(res.segments[0])])]
        rep = self._overlaps.add(g, n)  # the latest earlier window this one overlaps (repeats.repeat_of)
        self._steps.append({
            "step": i,
            "out_start": t,
            "out_end": t + n,
            "time_s": round(t / db.fps, 4),
            "recording": rec.name,
            "source_start_s": round((g - rec.start_frame) / db.fps, 4),
            "source_end_s": round((g + n - rec.start_frame) / db.fps, 4),
            "segment": int(res.segments[0]),
            "segment_start": int(res.starts[0]),
            "db_frame": g,
            "pose_dist": float(res.pose_dist[0]),
            "audio_dist": float(res.audio_dist[0]),
            "pose_rank": int(res.pose_rank[0]),
            "audio_rank": int(res.audio_rank[0]),
            "candidates": int(res.n_candidates[0]),
            "control": label[0] if label else None,
            "keyword": label[1] if label else None,
            "repeat_of": rep,
            "guard_relaxed": relaxed,
        })
        prev_frame = int(self._source[-2][-1]) if i > 0 else None
        if self._whole:  # one read of every window at the end (window_pieces: the same pieces)
            self._held.append((frames, t, prev_frame))
            return
        piece = window_piece(db, frames, t, prev_frame=prev_frame, seam_decay_s=self.seam_decay_s)
        self._pending.append(self._asm.add(piece, end=t + n))

    def _chunk(self, last=None) -> StreamChunk:
        parts = self._pending + ([last] if last is not None else [])
        self._pending = []
        J = len(self.db.skeleton.names)
        rot = np.concatenate([r for r, _ in parts]) if parts else np.zeros((0, J, 4))
        root = np.concatenate([x for _, x in parts]) if parts else np.zeros((0, 3))
        start = self._n_out
        self._n_out += rot.shape[0]
        if rot.shape[0]:
            self._rot.append(rot)
            self._root.append(root)
        done = [s for s in self._steps[self._steps_out:] if s["out_end"] <= self._n_out]
        self._steps_out += len(done)
        return StreamChunk(start=start, motion=chunk_motion(self.db.skeleton, self.fps, rot, root), steps=done)

    # -- the whole result ------------------------------------------------------------
    @property
    def n_steps(self) -> int:
        """Search steps run so far (the next step, which a :meth:`set_control` now affects, is this one)."""
        return len(self._windows)

    @property
    def n_frames_out(self) -> int:
        """Output frames returned so far."""
        return self._n_out

    @property
    def query(self) -> np.ndarray:
        """The standardised audio features of the speech so far, (T, Da) float32."""
        return self._query_buf[:self._n_query]

    def result(self, *, audio_path: str | None = None, options: dict | None = None) -> SynthResult:
        """Everything the finished stream made, as a :class:`SynthResult` (what ``synthesize`` returns)."""
        if not self._finished:
            raise ParameterError("Stream.result: finish() the stream first")
        db = self.db
        motion = Motion(skeleton=db.skeleton, fps=db.fps, rotations=np.concatenate(self._rot),
                        root_positions=np.concatenate(self._root))
        starts = np.array([w[0] for w in self._windows], dtype=np.int64)
        frames = [w[1] for w in self._windows]
        lengths = [w[2] for w in self._windows]
        repeats = dict(repeat_stats(frames, lengths, out_frames=starts, fps=db.fps),
                       guard_s=self.guard_s, guard_relaxed=int(sum(self._relaxed)))
        return SynthResult(motion=motion, source_frames=np.concatenate(self._source), boundaries=starts[1:],
                           steps=list(self._steps), fps=db.fps, audio_path=audio_path, options=options or {},
                           repeats=repeats)


#: The k-NN method in the registry (:mod:`gesturedb.synth.methods`).
METHOD = Method(
    name="knn",
    summary="rank-sum motion matching (Habibie et al. 2022)",
    options=SearchOptions,
    open=Searcher,
    settings=("segments", "scheduler", "parts"),
    streams=True,
    refines=True,
    systems=(
        EvalSystem("ranksum_pose", "rank-sum, pose pre-selection", "#1f77b4", {"preselect": "pose"}),
        EvalSystem("ranksum_audio", "rank-sum, audio pre-selection", "#2ca02c", {"preselect": "audio"}),
    ),
)
