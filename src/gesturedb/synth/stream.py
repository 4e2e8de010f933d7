"""Live synthesis: the k-NN search as the speech arrives (issue 39).

A :class:`Stream` takes speech in chunks of any size and gives back the output frames
as soon as no later audio can change them::

    stream = Stream(db, SearchOptions(control="left_wrist_high"), sample_rate=16000)
    for chunk in microphone():                   # float32 mono in [-1, 1]
        out = stream.push(chunk)                 # StreamChunk: out.start, out.motion, out.steps
        stream.set_control("slow")               # from the next step on
    last = stream.finish()

:meth:`gesturedb.synth.Searcher.synthesize` is this stream fed the whole file, so the
two cannot drift: the same speech and options give the same frames, bit for bit.

What a frame waits for (:attr:`Stream.latency_s`, the algorithmic latency):

* the search step that contains it: N frames (:data:`gesturedb.search.STEP_FRAMES`,
  8 at 15 fps, 0.53 s), as a step needs the audio features of all its frames;
* the audio features' context: half an FFT window after the frame's end (16 ms at 16 kHz,
  :class:`gesturedb.features.audio.AudioFeatureStream`);
* the feet (:class:`gesturedb.synth.contacts.FootPlanter`): whether a foot is planted is
  known :data:`gesturedb.synth.contacts.MAX_FILL_GAP_S` after the frame, and a step of the
  planted foot needs the motion up to its end (``STEP_S``, 0.67 s).

Placement, the pulls and the seams are causal (:class:`gesturedb.synth.assemble.PieceAssembler`).
The Savitzky-Golay smoothing (``smooth=True``) needs frames on both sides and is refused,
as is a refiner (it refines a whole utterance): synthesize the file for those.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gesturedb.control import compile_mask, full_mask
from gesturedb.control.schedule import _schedule_items
from gesturedb.db import keywords as kw
from gesturedb.errors import ParameterError, SearchError
from gesturedb.features.audio import AUDIO_WINDOW_S, AudioFeatureStream
from gesturedb.io.transcripts import Words, normalize_word
from gesturedb.motion import Motion
from gesturedb.search import _no_candidate_error
from gesturedb.synth.assemble import PieceAssembler, floor_height, typical_accelerations, window_piece, window_pieces
from gesturedb.synth.inputs import check_frames
from gesturedb.synth.options import SearchOptions
from gesturedb.synth.repeats import clear_frames, repeat_stats
from gesturedb.synth.result import SynthResult

__all__ = ["Stream", "StreamChunk"]


@dataclass
class StreamChunk:
    """What one :meth:`Stream.push` (or :meth:`Stream.finish`) made final.

    Attributes
    ----------
    start : int
        Output frame index of the chunk's first frame.
    motion : gesturedb.motion.Motion
        The new final frames at the database fps (``motion.n_frames`` may be 0).
    steps : list of dict
        Provenance of the search steps whose frames all became final, keys as
        :attr:`gesturedb.synth.result.SynthResult.steps` of the k-NN.
    """

    start: int
    motion: Motion
    steps: list = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return int(self.motion.rotations.shape[0])


def _motion(skeleton, fps, rot, root) -> Motion:
    if rot.shape[0]:
        return Motion(skeleton=skeleton, fps=fps, rotations=rot, root_positions=root)
    # Motion checks F >= 1 for what users build; a chunk may have no frame yet
    m = object.__new__(Motion)
    m.skeleton, m.fps, m.rotations, m.root_positions = skeleton, float(fps), rot, root
    return m


class Stream:
    """The k-NN synthesis of speech that arrives in chunks.

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

    ``Searcher.synthesize`` is a stream made with ``_whole=True``: every step as here, the frames
    assembled at :meth:`finish` (the kinematics of all frames at once: the same bits, faster).
    """

    def __init__(self, db, options: SearchOptions | None = None, *, sample_rate: int, searcher=None,
                 _whole: bool = False):
        from gesturedb.synth.matching import Searcher  # matching builds its synthesis on this module

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
        self._features = AudioFeatureStream(self.sample_rate, fps=db.fps, n_mfcc=int(db.config.get("n_mfcc", 13)))
        self._query = np.zeros((0, db.audio_mean.shape[0]), dtype=np.float32)
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
                                   seam_accel=typical_accelerations(db) if self.seam_decay_s > 0 else None,
                                   floor_y=floor_height(db), batch=_whole)
        self._whole = _whole
        self._held: list[tuple] = []  # _whole: the windows (frames, output frame, previous frame), read at finish
        self._windows: list[tuple[int, int, int]] = []  # (output frame, first database frame, length) per step
        self._steps: list[dict] = []
        self._relaxed: list[bool] = []
        self._source: list[np.ndarray] = []
        self._n_out = 0
        self._steps_out = 0
        self._rot, self._root = [], []  # every final frame, for result()
        self._pending = []  # (rotations, root) made final since the last chunk
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
        if self._finished:
            raise ParameterError("Stream.push: the stream is finished; start a new one")
        self._add_features(self._features.push(samples))
        while self._query.shape[0] - len(self._windows) * self.step >= self.step:
            self._run_step(self.step)
        return self._chunk()

    def finish(self) -> StreamChunk:
        """The remaining frames: the speech is over (its last step may be shorter)."""
        if self._finished:
            raise ParameterError("Stream.finish: the stream is already finished")
        self._add_features(self._features.finish())
        self._finished = True
        T = check_frames(self._query.shape[0], self.fps)
        while len(self._windows) * self.step < T:
            self._run_step(min(self.step, T - len(self._windows) * self.step))
        if self._held:
            for piece, (frames, t, _) in zip(window_pieces(self.db, self._held, seam_decay_s=self.seam_decay_s),
                                             self._held):
                self._pending.append(self._asm.add(piece, end=t + frames.shape[0]))
        return self._chunk(self._asm.finish())

    def _add_features(self, raw: np.ndarray) -> None:
        if raw.shape[0]:
            db = self.db
            q = ((raw.astype(np.float64) - db.audio_mean) / db.audio_std).astype(np.float32)
            self._query = np.concatenate([self._query, q])

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

    def _run_step(self, n: int) -> None:
        i = len(self._windows)
        t = i * self.step
        if i == 0:
            self.searcher._check_window(n)
        row, label, kw_row = self._step_rows(i, t, n)
        allowed = self._full if row is None else np.ascontiguousarray(row)
        q = self._query[t:t + n]
        recent = []  # the windows within the repeat guard: the latest ones
        for t0, g, m in reversed(self._windows):
            if t - t0 >= self._guard_frames:
                break
            recent.append((g, g + m))
        recent.reverse()
        res, relaxed = None, False
        try:
            if recent:
                try:
                    res = self._search(q, self._prev, clear_frames(allowed, recent)[None, :])
                except SearchError:
                    relaxed = True
            if res is None:
                try:
                    res = self._search(q, self._prev, allowed[None, :])
                except SearchError:
                    raise _no_candidate_error(i, t, n, self.searcher.seg_len, self._excl,
                                              None if row is None else allowed) from None
        except SearchError as exc:
            raise self.searcher._explain(exc, {i: label}, keyword_bits={i: kw_row}, exclude=self._excl,
                                         step=self.step, T=t + n) from None
        g = int(res.frames[0])
        db = self.db
        self._windows.append((t, g, n))
        self._relaxed.append(relaxed)
        self._prev = np.ascontiguousarray(db.rows("pose_features", [g + n - 1])[0], dtype=np.float32)
        frames = g + np.arange(n, dtype=np.int64)
        self._source.append(frames)
        rec = db.recordings[int(db.rows("frame_recording", np.array([g], dtype=np.int64))[0])]
        # the latest earlier window this one overlaps (repeats.repeat_of for the last window only)
        starts = np.fromiter((w[1] for w in self._windows[:-1]), dtype=np.int64, count=i)
        ends = starts + np.fromiter((w[2] for w in self._windows[:-1]), dtype=np.int64, count=i)
        hit = np.flatnonzero((starts < g + n) & (ends > g))
        rep = int(hit[-1]) if hit.size else None
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
        return StreamChunk(start=start, motion=_motion(self.db.skeleton, self.fps, rot, root), steps=done)

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
        return self._query

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
