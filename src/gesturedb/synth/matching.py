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
inertialized (an offset that decays to zero over ``seam_decay_s``, 0.4 s by
default; :mod:`gesturedb.synth.seams`); ``seam_decay_s=0`` copies the windows
back to back as in the paper.
"""
from __future__ import annotations

import numpy as np

from gesturedb.control import candidate_counts, mask_and, suggest_percentiles
from gesturedb.errors import ParameterError, SearchError
from gesturedb.features.audio import audio_deltas
from gesturedb.search import HalfPose, PoseProjection, rank_sum_search
from gesturedb.synth import inputs
from gesturedb.synth.assemble import assemble_frames
from gesturedb.synth.inputs import speech_samples  # noqa: F401  (its old home; every method's now)
from gesturedb.synth.options import (  # noqa: F401  (re-exported from their old home)
    DEFAULT_INIT, INIT_CHOICES, STEP_S, SearchOptions, default_step,
)
from gesturedb.synth.protocol import EvalSystem, Method
from gesturedb.synth.repeats import check_guard_s
from gesturedb.synth.result import SynthResult
from gesturedb.synth.stream import Stream
from gesturedb.synth.seams import SEAM_DECAY_S, check_decay_s


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
        built at the first pose search): identical results, an eighth of the
        bytes per step. On by
        default (skipped when it would keep a quarter of the candidates or
        more); takes precedence over ``half_precision``.
    client : distributed.Client, optional
        Search over ``parts`` shards resident on this Dask cluster's workers
        (:class:`gesturedb.db.shards.ShardedSearch`, built at the first
        search): exactly the same output as the search in this process.
    parts : int
        Number of shards with ``client``. A database opened from an index file
        (``gesturedb shard``) is searched over its own shard files instead, each
        read by a worker (:meth:`ShardedSearch.from_shard_files`).
    """

    def __init__(self, db, *, segments: str = "chunks", half_precision: bool = False,
                 projection: bool = True, client=None, parts: int = 2):
        self.db = db
        self._client, self._parts, self._sharded = client, parts, None
        self._projection = bool(projection)
        self._proj = None
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

    def pose_projection(self):
        """The :class:`gesturedb.search.PoseProjection` of the database's pose
        features, built once; None when ``projection=False`` or when it would
        keep a quarter of the candidates or more (pose features without the
        structure of motion: the filter would only add work)."""
        if self._projection and self._proj is None:
            # binary16 rows: half the stream of float32 rows for a few more exact checks
            self._proj = PoseProjection(self.db.pose_features, half=True)
            if self._proj.keep_fraction >= 0.25:
                self._projection = False
                self._proj = None
        return self._proj

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

    def stream(self, options: SearchOptions | None = None, *, sample_rate: int) -> Stream:
        """A live synthesis over this searcher (:class:`gesturedb.synth.stream.Stream`)."""
        return Stream(self.db, options, sample_rate=sample_rate, searcher=self)

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
                    from gesturedb.db.shards import ShardedSearch  # Dask, only with a client

                    self._sharded = ShardedSearch.for_database(db, self.seg_start, self.seg_len,
                                                               scheduler=self._client, parts=self._parts)
                return self._sharded.search(q, prev, step=step, k=k, preselect=preselect,
                                            allowed=allowed_now, exclude=excl)
            return rank_sum_search(
                db.pose_features, db.audio_features, self.seg_start, self.seg_len, q, prev,
                step=step, k=k, preselect=preselect, exclude=excl, pose_f16=self._half,
                allowed=None if allowed_now is None else np.ascontiguousarray(allowed_now),
                pose_proj=self.pose_projection() if preselect == "pose" else None,
            )

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


#: The k-NN method in the registry (:mod:`gesturedb.synth.methods`).
METHOD = Method(
    name="knn",
    summary="rank-sum motion matching (Habibie et al. 2022)",
    options=SearchOptions,
    open=Searcher,
    settings=("segments", "client", "parts"),
    streams=True,
    refines=True,
    systems=(
        EvalSystem("ranksum_pose", "rank-sum, pose pre-selection", "#1f77b4", {"preselect": "pose"}),
        EvalSystem("ranksum_audio", "rank-sum, audio pre-selection", "#2ca02c", {"preselect": "audio"}),
    ),
)
