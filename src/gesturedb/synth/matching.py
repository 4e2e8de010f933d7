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

import os

import numpy as np

from gesturedb.errors import ParameterError, SearchError
from gesturedb.synth.assemble import assemble_frames
from gesturedb.synth.seams import SEAM_DECAY_S, check_decay_s
from gesturedb.synth.repeats import DEFAULT_REPEAT_GUARD_S, check_guard_s, guarded_search, repeat_of, repeat_stats
from gesturedb.synth.result import SynthResult

#: Initial-pose choices of :meth:`Searcher.initial_pose`.
INIT_CHOICES = ("random", "mean")
#: The default initial pose: a seeded random database frame, the paper's setting
#: for all its experiments (Habibie et al. 2022, Sec. 4) and the start of every
#: path the refiner is trained on (gesturedb.refiner.data), so that a refined
#: synthesis sees the kind of path its refiner learnt from. The mean pose is an
#: average no one holds; on the held-out BEAT2 stretch its path moved the pelvis
#: at 1.41x the capture's speed against 0.92x from seed 0 and 1.02x on average
#: over seeds 0-7 (README, "The body slides"); on the four inputs both were
#: within the capture's range.
DEFAULT_INIT = "random"


#: The paper's search step, N = 8 frames at its 15 fps, in seconds: a database of another frame rate steps
#: as often in time (16 frames at 30 fps). At 30 fps with 8-frame steps the seams came twice as often and the
#: seam/inside jerk was 1.18-1.23 on the four BEAT2 inputs; with 16, 1.06-1.10 (15 fps: 0.85-1.08).
STEP_S = 8.0 / 15.0


def default_step(fps: float) -> int:
    """Frames per search step at ``fps``: :data:`STEP_S` rounded, at least 1."""
    return max(1, int(round(STEP_S * float(fps))))


def speech_samples(db, audio, sr: int | None = None):
    """Speech as mono samples at the database's analysis rate: ``(samples, sr, path or None)``.

    ``audio`` is a WAV path (read and resampled) or an array of mono samples
    whose rate ``sr`` must then be given. Shared by every synthesis method.
    """
    from gesturedb.io.audio import read_audio

    if isinstance(audio, (str, os.PathLike)):
        path = os.fspath(audio)
        samples, sr = read_audio(path, sr=int(db.config.get("sample_rate", 16000)))
        return samples, sr, path
    if sr is None:
        raise ParameterError("sr: expected the sample rate of the samples given as audio, got None")
    return np.asarray(audio, dtype=np.float32), sr, None


class Searcher:
    """Search an open database for new speech.

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
        self._half = None
        if half_precision:
            from gesturedb.search import HalfPose

            self._half = HalfPose(db.pose_features)
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
            from gesturedb.search import PoseProjection

            # binary16 rows: half the stream of float32 rows for a few more exact checks
            self._proj = PoseProjection(self.db.pose_features, half=True)
            if self._proj.keep_fraction >= 0.25:
                self._projection = False
                self._proj = None
        return self._proj

    # -- inputs ---------------------------------------------------------------
    def query_features(self, samples: np.ndarray, sr: int) -> np.ndarray:
        """Audio features of new speech, standardised like the database's.

        Returns
        -------
        ndarray [shape=(T, 14)], float32, T = the speech duration in database frames.
        """
        from gesturedb.features.audio import audio_features, n_frames_for_duration

        T = n_frames_for_duration(samples.shape[0] / sr, self.db.fps)
        if T < 1:
            raise ParameterError(f"audio: expected at least one frame ({1 / self.db.fps:.3f} s) of speech, got {samples.shape[0] / sr:.3f} s")
        n_mfcc = int(self.db.config.get("n_mfcc", 13))
        raw = audio_features(samples, sr, fps=self.db.fps, n_frames=T, n_mfcc=n_mfcc).astype(np.float64)
        return ((raw - self.db.audio_mean) / self.db.audio_std).astype(np.float32)

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

    def exclude_recordings(self, names) -> np.ndarray | None:
        """bool per segment: True for segments of the named recordings (e.g. a query's own recording)."""
        if not names:
            return None
        idx = {self.db.recording(n).index for n in names}
        # a mirrored copy is the same performance: leave it out too
        for r in self.db.recordings:
            if r.name.removesuffix("~mirror") in {self.db.recordings[i].name.removesuffix("~mirror") for i in idx}:
                idx.add(r.index)
        return np.isin(self.seg_recording, sorted(idx))

    # -- the search -----------------------------------------------------------
    def synthesize(
        self,
        audio,
        *,
        sr: int | None = None,
        transcript=None,
        k: int = 1,
        preselect: str = "pose",
        init: str = DEFAULT_INIT,
        seed: int | None = 0,
        step: int | None = None,
        seam_decay_s: float = SEAM_DECAY_S,
        smooth: bool = False,
        control=None,
        keywords=True,
        exclude=None,
        refiner=None,
        speaker: str | None = None,
        repeat_guard_s: float = DEFAULT_REPEAT_GUARD_S,
    ) -> SynthResult:
        """Synthesize gestures for speech.

        Parameters
        ----------
        audio : path or ndarray [shape=(n,)]
            A WAV file, or mono samples with ``sr``.
        transcript : path, Words or None
            Word timings of the speech; needed for keyword sub-databases.
        k : int
            Take the k-th best candidate of each step (1 = best).
        preselect : {"pose", "audio"}
        init : {"random", "mean"}
            Initial previous pose: a database frame drawn with ``seed`` (default,
            as the paper's experiments) or the mean pose.
        step : int, optional
            N, frames per search step (default :func:`default_step`: 8 at 15 fps, 16 at 30 fps).
        seam_decay_s : float
            Seconds over which the offset at a window boundary decays (0 = back-to-back
            copies as in the paper); see :mod:`gesturedb.synth.seams`.
        smooth : bool
            Savitzky-Golay smoothing of the result (GestureMaster's, window in seconds);
            off by default: it removes beat strokes.
        control : str, list or None
            A control schedule (``"0-12: left_wrist_height > p85; 12-: slow"``) or one
            mask expression for the whole synthesis; see :mod:`gesturedb.control`.
        keywords : bool or list of str
            Use keyword sub-databases for the steps that overlap their words
            (True: all of the database's, False: none, a list: only those).
        exclude : list of str
            Recordings whose segments are left out of the search.
        refiner : object with ``refine(motion, audio)``, optional
            Applied to the assembled motion in one pass, e.g. a trained
            :class:`gesturedb.refiner.train.Refiner` (``audio`` is the query's
            standardised features and their deltas, (T, 28)). Any object with
            that method works, so synthesis does not depend on the refiner stage.
        speaker : str, optional
            Search only this speaker's recordings (``recordings/speaker``) of a
            multi-speaker database.
        repeat_guard_s : float
            A database window used within this many seconds of output is taken out
            of the step's allowed set (:mod:`gesturedb.synth.repeats`; 0 = off, the
            paper's search). Steps the guard would leave without a candidate run
            without it.

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
        from gesturedb.search import rank_sum_search

        db = self.db
        samples, sr, audio_path = speech_samples(db, audio, sr)
        if step is None:
            step = default_step(db.fps)
        if not isinstance(step, (int, np.integer)) or step < 1:
            raise ParameterError(f"step: expected a positive number of frames, got {step!r}")
        seam_decay_s = check_decay_s(seam_decay_s)
        n_seg = len(self.seg_start)
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= max(n_seg, 1):
            raise ParameterError(f"k: expected an integer from 1 to the number of {self.segments_kind} of "
                                 f"{db.path} ({n_seg}), got {k!r}")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))
                                 or not 0 <= seed < 2**63):
            raise ParameterError(f"seed: expected an integer from 0 to 2**63-1, got {seed!r}")
        if isinstance(transcript, (str, os.PathLike)):
            # a given file is always read and checked, even when no keyword sub-database will use it
            from gesturedb.io.transcripts import read_transcript

            transcript = read_transcript(transcript)
        if transcript is not None:
            from gesturedb.io.transcripts import check_words_fit

            check_words_fit(transcript, samples.shape[0] / sr, audio=audio_path)
        query = self.query_features(samples, sr)
        T = query.shape[0]
        if T < step:
            raise ParameterError(
                f"audio: expected at least one search step ({step} frames = {step / db.fps:.2f} s), "
                f"got {T} frames ({T / db.fps:.2f} s){' in ' + audio_path if audio_path else ''}"
            )
        if int(self.seg_len.max(initial=0)) < min(step, T) + 1:
            raise ParameterError(
                f"database {db.path}: no {self.segments_kind} segment is long enough for a window of "
                f"{min(step, T)} frames plus its entry frame (longest: {int(self.seg_len.max(initial=0))} frames)"
            )
        n_steps = (T + step - 1) // step
        allowed, labels, keyword_bits = self._step_masks(control, transcript, keywords, n_steps=n_steps, step=step, T=T)
        excl = self.exclude_recordings(exclude)
        if speaker is not None:
            others = ~np.isin(self.seg_recording, [r.index for r in db.speaker_recordings(speaker)])
            excl = others if excl is None else (excl | others)
        guard_s = check_guard_s(repeat_guard_s)
        init_pose = self.initial_pose(init, seed=seed)

        def search(q, prev, allowed_now):
            if self._client is not None:
                if self._sharded is None:
                    from gesturedb.db.shards import ShardedSearch

                    self._sharded = ShardedSearch.for_database(db, self.seg_start, self.seg_len,
                                                               client=self._client, parts=self._parts)
                return self._sharded.search(q, prev, step=step, k=k, preselect=preselect,
                                            allowed=allowed_now, exclude=excl)
            return rank_sum_search(
                db.pose_features, db.audio_features, self.seg_start, self.seg_len, q, prev,
                step=step, k=k, preselect=preselect, exclude=excl, pose_f16=self._half,
                allowed=None if allowed_now is None else np.ascontiguousarray(allowed_now),  # StepBitsets: the array
                pose_proj=self.pose_projection() if preselect == "pose" else None,
            )

        relaxed = np.zeros(n_steps, dtype=bool)
        try:
            if guard_s > 0:
                # the guard's mask for a step depends on the windows before it: one kernel call per step
                from gesturedb.control import full_mask
                from gesturedb.search import SearchResult, _no_candidate_error

                d = guarded_search(search, query=query, init_pose=init_pose, step=step,
                                   pose_row=lambda f: db.rows("pose_features", [f])[0],
                                   allowed=allowed, full=full_mask(db.n_frames),
                                   guard_frames=int(round(guard_s * db.fps)),
                                   no_candidate=lambda i, t, n, row: _no_candidate_error(
                                       i, t, n, self.seg_len, excl, None if allowed is None else row))
                relaxed = d.pop("relaxed")
                res = SearchResult(n_frames=T, **d)
            else:
                res = search(query, init_pose, allowed)
        except SearchError as exc:
            raise self._explain(exc, labels, keyword_bits=keyword_bits, exclude=excl, step=step, T=T) from None
        rep_of = repeat_of(res.frames, res.lengths)

        source = res.frame_map()
        steps = []
        recs = db.recordings
        rec_of = db.rows("frame_recording", np.asarray(res.frames, dtype=np.int64))
        for i in range(len(res.segments)):
            t, g, n = int(res.out_frames[i]), int(res.frames[i]), int(res.lengths[i])
            rec = recs[int(rec_of[i])]
            label = labels[i] if labels is not None else None
            steps.append({
                "step": i,
                "out_start": t,
                "out_end": t + n,
                "time_s": round(t / db.fps, 4),
                "recording": rec.name,
                "source_start_s": round((g - rec.start_frame) / db.fps, 4),
                "source_end_s": round((g + n - rec.start_frame) / db.fps, 4),
                "segment": int(res.segments[i]),
                "segment_start": int(res.starts[i]),
                "db_frame": g,
                "pose_dist": float(res.pose_dist[i]),
                "audio_dist": float(res.audio_dist[i]),
                "pose_rank": int(res.pose_rank[i]),
                "audio_rank": int(res.audio_rank[i]),
                "candidates": int(res.n_candidates[i]),
                "control": label[0] if label else None,
                "keyword": label[1] if label else None,
                "repeat_of": rep_of[i],
                "guard_relaxed": bool(relaxed[i]),
            })
        starts = np.asarray(res.out_frames, dtype=np.int64)
        motion = self.assemble(source, starts, seam_decay_s=seam_decay_s, smooth=smooth)
        if refiner is not None:
            from gesturedb.features.audio import audio_deltas

            motion = refiner.refine(motion, np.concatenate([query, audio_deltas(query)], axis=1))
        options = dict(k=k, preselect=preselect, init=init, seed=seed, step=step, seam_decay_s=seam_decay_s, smooth=smooth,
                       control=control if isinstance(control, (str, type(None))) else str(control),
                       keywords=keywords if isinstance(keywords, bool) else list(keywords),
                       segments=self.segments_kind, database=db.path,
                       refiner=None if refiner is None else str(getattr(refiner, "path", None) or type(refiner).__name__),
                       speaker=speaker, repeat_guard_s=guard_s)
        repeats = dict(repeat_stats(res.frames, res.lengths, out_frames=res.out_frames, fps=db.fps),
                       guard_s=guard_s, guard_relaxed=int(relaxed.sum()))
        return SynthResult(motion=motion, source_frames=source, boundaries=starts[1:], steps=steps,
                           fps=db.fps, audio_path=audio_path, options=options, repeats=repeats)

    # -- masks ------------------------------------------------------------------
    def _step_masks(self, control, transcript, keywords, *, n_steps, step, T):
        """Per-step allowed bitsets and keyword bitsets (:class:`gesturedb.control.StepBitsets`) and the
        (control, keyword) label of each step; Nones when unconstrained."""
        from gesturedb.control import schedule_bitsets

        hooks = []
        keyword_bits = None
        if control:
            # one bare expression applies to the whole synthesis
            sched = [(0.0, None, control)] if isinstance(control, str) and ":" not in control else control
            res = schedule_bitsets(
                sched, controls=self.db.control_datasets, named=self.db.mask_datasets, n_steps=n_steps, step=step,
                fps=self.db.fps, n_out_frames=T, n_frames=self.db.n_frames,
            )
            hooks.append(("control", res.steps, res.labels))
        if keywords and transcript is not None:
            from gesturedb.db import keywords as kw

            res = kw.keyword_step_masks(self.db, transcript, n_steps=n_steps, step=step, n_out_frames=T,
                                        only=None if keywords is True else list(keywords), compact=True)
            if res is not None:
                hooks.append(("keyword", *res))
                keyword_bits = res[0]
        if not hooks:
            return None, None, None
        # StepBitsets: each distinct row once, not steps x F / 8 bytes
        allowed = None
        labels = [[None, None] for _ in range(n_steps)]
        for kind, bits, lab in hooks:
            allowed = bits if allowed is None else allowed & bits
            for i in range(n_steps):
                if lab[i] is not None:
                    labels[i][0 if kind == "control" else 1] = lab[i]
        labels = [tuple(x) if any(v is not None for v in x) else None for x in labels]
        return allowed, labels, keyword_bits

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
            from gesturedb.control import candidate_counts, mask_and, suggest_percentiles

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
