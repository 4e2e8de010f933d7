"""GestureMaster (Zhou et al. 2022, Sec. 3-4): speech -> gestures by a path through the motion graph.

The graph (nodes = the database's word-gap clips, mirrored copies included) and the style
predictor are built with the database (:mod:`gesturedb.db.graph`). For new speech:

1. **Input clips.** The speech is split at pauses longer than ``gap_s`` (default: the
   database's own ``gap_s``), from the transcript when given. Without a transcript, pauses
   and word-like onsets come from a voice-activity detector (:func:`voiced_segments`: Silero
   VAD by default, or the energy detector; voiced stretches separated by >= 80 ms of silence
   count as "words"; measured accuracy in :mod:`gesturedb.features.pauses`). Input clips longer
   than the longest database clip are split at their deepest pause (or in the middle),
   so every clip has a node that can be fitted to it.
2. **Signatures.** Rhythm: word onsets over 32 bins (Sec. 3.2). Style: predicted from the
   clip's audio by the ridge model stored with the graph.
3. **Data term** ``C_d = l5 * |style_in - style_d| + l6 * H(rhythm_in, rhythm_motion_d)
   + l_dur * |log(len_d / len_i)|`` (+1000 if the clip cannot be fitted even with its
   continuation in its recording: never impossible, always avoided). ``+inf`` where a
   control mask or keyword excludes the node (rules: for a control, node ``d`` is allowed for
   clip ``i`` when at least half of ``d``'s frames are in the mask active at ``i``'s middle
   frame; a clip that speaks a keyword of a keyword sub-database takes a node that overlaps
   one of the speaker's own occurrences of it, see ``GraphSynthesizer._apply_masks``).
   ``H`` is the paper's Hamming distance with what the signatures' numbers of bits explain taken out
   (:func:`gesturedb.features.rhythm.hamming_beyond_chance`; ``rhythm="hamming"``: the paper's): the
   plain distance of a sparse speech signature prefers motion with few speed minima, calm clips.
4. **Search.** :func:`viterbi` minimises ``l3 * sum C_d + l4 * sum T`` exactly
   (``../shared/spec/graph.md``) over the upper-body graph. Defaults from Sec. 5: l3 = 1,
   l4 = 3, l5 = 1, l6 = 0.1. The graph has no self-edges, so the same clip is never played
   twice in a row. The lower body has its own search (below).
5. **Fitting.** Each chosen upper-body clip is fitted to its input clip at ``clamp(len_d / len_i, 1/1.25,
   1.25)`` times its length without changing its pace (:func:`fit_times`): the surplus frames are cut out,
   or the missing ones played twice, where its hands are slowest, a seam like the others (played faster
   or slower, its velocity power above 2 Hz changed as about the 4th power of the rate). Where it is still
   longer it is trimmed, where shorter it runs on into its recording's following frames. Pieces go
   through :func:`gesturedb.synth.assemble.assemble_pieces` (placement, seams inertialized
   as for the k-NN). GestureMaster's Savitzky-Golay filter per joint group (Sec. 4.2:
   window 7 frames at its 30 fps, order 2 for arms, hands and head; order 1 for the rest
   and the root) is ``smooth=True``, off by default: its window, kept in seconds, still
   removes beat strokes.

Two graphs (Sec. 4.1), one path each over the same input clips: the upper body (spine, arms,
hands, head) follows the path that minimises the whole cost above over the upper-body graph;
the lower body (root and legs: where the speaker stands, the pelvis' tilt, the stance) follows
the path of least transition cost over the lower-body graph, its data term the duration
term (the paper sets the lower body's data term to 0; the duration term makes the graph's
transition cost, measured at the end of a node, the one that plays), a stepping term (a node
whose feet move more than the database's median clip costs the log of the ratio: transitions
alone chose the stretches where the speaker walks about) and the penalty for a node whose
recording ends before the clip does. The lower body carries no rhythm, so it is
not fitted: each node plays as it is, trimmed or run on into its recording (time-warped,
as the upper body once was, its feet slid: on the four BEAT2 inputs with 30 nodes, skating
0.085 against 0.064 m/s unwarped). The two motions are joined: upper-body local rotations
from the first (the spine's first joint keeping its own orientation in the world, less the
heading, :func:`join_upper_body`), root and legs from the second (feet planted on those).

Offline only (``METHOD.streams`` is False): an input clip ends at the next pause longer than
``gap_s``, its style comes from its whole audio and its node is fitted to its whole length,
and the exact path search (:func:`viterbi`) chooses every clip knowing all the others; a
live graph would wait a phrase (seconds) before its first frame. The k-NN streams
(:class:`gesturedb.synth.stream.Stream`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gesturedb import rotations as R
from gesturedb.db.graph import body_parts, clip_audio_inputs, predict_style, suggest_gap_s
from gesturedb.errors import InputFileError, ParameterError, SchemaError
from gesturedb.features.body import BODY_ROLES
from gesturedb.features.pauses import DEFAULT_VAD, voiced_segments
from gesturedb.features.rhythm import audio_rhythm, hamming, hamming_beyond_chance, hand_speed, speed_minima
from gesturedb.features.segments import word_gap_clips
from gesturedb.io.joints import find_joints
from gesturedb.io.transcripts import Words
from gesturedb.motion import Motion
from gesturedb.roles import WRIST_ROLES
from gesturedb.synth import inputs
from gesturedb.synth.assemble import (
    SMOOTH_WINDOW_S,
    Piece,
    _yaw_of,
    _yaw_quat,
    assemble_pieces,
    floor_height,
    placed_frames,
    savgol_smooth,
    typical_accelerations,
)
from gesturedb.synth.contacts import foot_joints
from gesturedb.synth.options import SynthOptions
from gesturedb.synth.protocol import EvalSystem, Method
from gesturedb.synth.result import SynthResult
from gesturedb.synth.seams import LEAD_FRAMES, check_decay_s
from gesturedb.synth.viterbi import viterbi

__all__ = ["viterbi", "GraphSynthesizer", "GraphOptions", "voiced_segments", "MAX_SPEED", "METHOD"]

#: a clip is fitted (:func:`fit_times`) to 1/MAX_SPEED .. MAX_SPEED times its own length; beyond, trimmed or run on
MAX_SPEED = 1.25
#: A speed minimum of a clip is a hold where a cut may go (:func:`fit_times`) when its hand speed is below this
#: fraction of the clip's median hand speed.
HOLD_SPEED_FRACTION = 0.5
#: penalty added to C_d when a clip cannot be fitted even with its continuation
UNFIT_PENALTY = 1000.0
#: Added to the data cost of a node without the keyword for a clip that speaks one: far above the
#: style, rhythm and duration terms (a few units), below UNFIT_PENALTY (a clip that cannot be fitted
#: is worse than a phrase without the keyword).
KEYWORD_MISS_PENALTY = 100.0
#: shortest piece a long input clip is split into, frames
MIN_CLIP = 8
ORDER2_PARTS = ("shoulder", "elbow", "wrist", "hand", "arm", "index", "middle", "ring", "pinky", "thumb",
                "head", "neck", "jaw", "eye", "collar", "finger")


def join_upper_body(skeleton, rot: np.ndarray, upper_rot: np.ndarray, upper_joints) -> np.ndarray:
    """Keep the upper body's own orientation in the world when it rides on another path's pelvis.

    ``rot`` (T, J, 4) holds the lower path's rotations with the upper joints' local rotations
    already copied from ``upper_rot``. An upper joint whose parent is a lower-body joint (the
    spine's first joint, a child of the pelvis) gets the local rotation that gives it its world
    rotation in the upper path, turned about +y by the difference of the two pelvises' headings.
    In a capture the spine compensates the pelvis's sway and tilt; copied as local rotations onto
    another pelvis those compensations moved the head instead (its 4-7 Hz power 8-11x the
    database's on the BEAT2 inputs, against about 1x for either path alone).
    """

    upper = set(int(j) for j in np.asarray(upper_joints).ravel())
    parents = np.asarray(skeleton.parents)
    roots = [j for j in sorted(upper) if parents[j] >= 0 and int(parents[j]) not in upper]
    if not roots:
        return rot
    out = rot.copy()
    for j in roots:
        p = int(parents[j])
        if p != 0:
            continue  # only a child of the root joint can be re-parented by the pelvis's world rotation alone
        turn = _yaw_quat(_yaw_of(rot[:, 0]) - _yaw_of(upper_rot[:, 0]))
        world = R.multiply(turn, R.multiply(upper_rot[:, 0], upper_rot[:, j]))
        out[:, j] = R.multiply(R.inverse(rot[:, 0]), world)
    return out


def fit_times(hand: np.ndarray, n: int, speed: float, *, fps: float,
              margin: int = LEAD_FRAMES) -> tuple[np.ndarray, list[int]]:
    """Source times (n,), in frames from a clip's first, that fit the clip to ``n`` output frames where
    it has ``n + k`` (``k = round((n - 1) * (speed - 1))``), and the output frames where a cut resumes it.

    The clip is not resampled: played uniformly at 1.25x, its arms' velocity power above 2 Hz was
    2.2-2.6x what the same clips carry at their own pace (on the BEAT2 database's clips; it grows as
    about ``speed ** 4``, the spectrum falling steeply and moving up), at 0.8x 0.26-0.28x; weighting the
    warp towards the holds (slow hands) was no better above 4 Hz. Instead frames are cut out (``k > 0``)
    or played twice (``k < 0``) just before the clip's speed minima where its hands rest
    (:func:`gesturedb.features.rhythm.speed_minima` of ``hand`` slower than :data:`HOLD_SPEED_FRACTION`
    of its median: moments its rhythm signature marks), each cut putting the minimum where the uniform
    warp would (``p / speed``), so the rhythm stays where the graph's rhythm term placed it (one cut at
    the slowest span shifted it by up to ``|k|`` frames: rhythm agreement 0.85 bits worse on the BEAT2
    inputs, 0.55 this way); the last cut takes the rest. Between cuts the clip keeps its own pace; it
    still starts and ends where its word gaps and the graph's transition costs are. Cuts are at least
    ``margin`` frames from the clip's ends and one frame apart; each is a seam, treated like the others.
    Without such a minimum: one cut at the span of least summed hand speed; without room for that: the
    uniform warp.

    Parameters
    ----------
    hand : ndarray [shape=(m,)], m/s
        Hand speed of the clip's source frames from its first on (at least ``n + k`` of them).
    n : int
        Output frames.
    speed : float > 0
        The clip's length over the output's.
    fps : float
        Frame rate (the minima's window is in seconds).
    """
    k = int(round((n - 1) * (float(speed) - 1.0)))
    if k == 0:
        return np.arange(n, dtype=np.float64), []
    m = n + k  # source frames played
    uniform = (np.arange(n) * float(speed), [])
    if hand.size < m or m < 2 * margin + 1 or n < 2 * margin + 1:
        return uniform
    h = np.asarray(hand[:m], dtype=np.float64)
    # (leave, resume) source frames of every cut: the clip plays up to leave - 1, then resume on
    cuts, done = [], 0  # done: frames cut so far (negative: repeated)
    mins = speed_minima(h, fps=fps)
    # only where the hands rest (slower than half the clip's median): cut at every minimum, the seams in
    # moving hands put 2_scott_0_2_2 at 1.67x the database's arm power at 4-7 Hz, seam/inside jerk 1.22
    for p in mins[h[mins] < HOLD_SPEED_FRACTION * np.median(h)]:
        want = int(p) - int(round(p / speed))  # frames cut before p for it to play at p / speed
        d = want - done
        if d == 0:
            continue
        # the minimum itself plays where it is wanted: the skipped frames are those just before it (the cut
        # resumes at it), the repeated ones those just before it (the cut leaves from it)
        leave = int(p) - d if d > 0 else int(p)
        if not _cut_fits(cuts, leave, leave + d, m, margin):
            continue
        cuts.append((leave, leave + d))
        done = want
    rest = k - done
    if rest:
        if cuts:  # the last cut takes the rest, where it fits; otherwise a cut of its own
            leave, resume = cuts[-1]
            if _cut_fits(cuts[:-1], leave, resume + rest, m, margin):
                cuts[-1] = (leave, resume + rest)
                rest = 0
        if rest:
            c = _slowest_cut(h, cuts, rest, m, margin)
            if c is None:
                return uniform
            cuts.append(c)
            cuts.sort()
    t, out, src, o = np.empty(n), [], 0, 0
    for leave, resume in cuts + [(m, m)]:
        seg = leave - src
        t[o:o + seg] = np.arange(src, leave)
        o += seg
        if leave < m:
            out.append(o)
        src = resume
    return t, out


def _cut_fits(cuts, leave, resume, m, margin) -> bool:
    """Whether a cut (play up to ``leave - 1``, then ``resume`` on) fits after ``cuts``: every source frame it
    plays inside the clip, ``margin`` frames of the clip kept at either end, one frame at least between cuts."""
    prev = cuts[-1][1] if cuts else 0  # where the last cut resumed (margin >= 1 covers the first cut)
    return leave >= max(prev + 1, margin) and resume >= max(prev, margin) and max(leave, resume) <= m - margin


def _slowest_cut(h, cuts, d, m, margin):
    """A cut of ``d`` frames (repeated where negative) where the summed hand speed over its span is least,
    after the last of ``cuts``; None where none fits."""
    cs = np.concatenate([[0.0], np.cumsum(h)])
    best = None
    for leave in range(margin, m - margin + 1):
        if not _cut_fits(cuts, leave, leave + d, m, margin):
            continue
        a, b = min(leave, leave + d), max(leave, leave + d)
        cost = cs[min(b + 1, m)] - cs[a]
        if best is None or cost < best[0]:
            best = (cost, leave)
    return None if best is None else (best[1], best[1] + d)


def _split_long(bounds: list[int], w_start, w_end, fps: float, max_len: int) -> list[int]:
    """Split clips [b_k, b_{k+1}) longer than ``max_len`` frames at their deepest inner pause, else mid."""
    out = [bounds[0]]
    for a, b in zip(bounds[:-1], bounds[1:]):
        stack = [(a, b)]
        pieces = []
        while stack:
            lo, hi = stack.pop()
            if hi - lo <= max_len:
                pieces.append((lo, hi))
                continue
            # candidate cuts: the middle of every pause between two words, at least MIN_CLIP frames inside
            run_end = np.maximum.accumulate(w_end)[:-1] if w_end.size else np.zeros(0)
            gaps = w_start[1:] - run_end
            cuts = np.rint((run_end + w_start[1:]) / 2 * fps).astype(np.int64)
            inner = (cuts >= lo + MIN_CLIP) & (cuts <= hi - MIN_CLIP)
            cut = (lo + hi) // 2
            if inner.any():
                cut = int(cuts[inner][np.argmax(gaps[inner])])
            stack += [(cut, hi), (lo, cut)]
        out += [hi for _, hi in sorted(pieces)]
    return out


@dataclass(frozen=True)
class GraphOptions(SynthOptions):
    """The motion graph's options (:meth:`GraphSynthesizer.synthesize`): the shared ones and

    Attributes
    ----------
    gap_s : float or "auto", optional
        Pause that splits the input (None: the database's ``gap_s``; "auto": from the
        input's own pauses, clips of about 3 s, :func:`gesturedb.db.graph.suggest_gap_s`).
    vad : "silero" or "energy"
        The detector :func:`voiced_segments` uses when there is no transcript.
    w_data, w_trans, l5, l6 : float
        lambda_3, lambda_4, lambda_5, lambda_6 (Sec. 5: 1, 3, 1, 0.1).
    l_dur : float
        Weight of the duration term ``|log(len_d / len_i)|``.
    rhythm : "chance" or "hamming"
        The rhythm term: the Hamming distance beyond chance
        (:func:`gesturedb.features.rhythm.hamming_beyond_chance`, the default) or the paper's plain
        Hamming distance, which prefers calm clips (module doc, step 3; ``docs/evaluation.md``).

    ``control``, ``keywords``, ``exclude`` and ``speaker`` restrict nodes by the rules in the
    module doc; ``smooth`` is GestureMaster's Savitzky-Golay filter per joint group.
    """

    gap_s: float | str | None = None
    vad: str = DEFAULT_VAD
    w_data: float = 1.0
    w_trans: float = 3.0
    l5: float = 1.0
    l6: float = 0.1
    l_dur: float = 0.5
    rhythm: str = "chance"


#: The rhythm terms of :class:`GraphOptions` and the function of each.
RHYTHM_TERMS = {"chance": hamming_beyond_chance, "hamming": hamming}


class GraphSynthesizer:
    """GestureMaster synthesis over an open database that has a motion graph.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    """

    def __init__(self, db):
        self.db = db
        if not db.has_motion_graphs:
            raise SchemaError(db.path, f"graph: no motion graphs in this database; run `gesturedb graph {db.path}`")
        # (indptr, indices, cost) of each: upper body = rhythm, style and transitions; lower body
        # (root and legs) = transitions only
        self.upper_graph, self.lower_graph = db.motion_graph("upper"), db.motion_graph("lower")
        self.upper_joints, self.lower_joints = body_parts(db.skeleton.names, db.skeleton.parents)
        self.style_model = db.style_model
        c = db.clips
        self.start = np.asarray(c.start, dtype=np.int64)
        self.length = np.asarray(c.length, dtype=np.int64)
        self.recording = np.asarray(c.recording, dtype=np.int64)
        self.rhythm_motion = np.asarray(c.rhythm_motion, dtype=np.uint32)
        self.style = np.asarray(c.style, dtype=np.float64)
        rec_end = np.array([r.start_frame + r.n_frames for r in db.recordings], dtype=np.int64)
        self.avail = rec_end[self.recording] - self.start  # frames from clip start to its recording's end
        self.rec_start = np.array([r.start_frame for r in db.recordings], dtype=np.int64)[self.recording]
        self.stepping = self._stepping()
        # the roles the hand speed needs (the database's feature joints), None where it lacks them
        try:
            self._hand_joints = find_joints(db.skeleton.names, WRIST_ROLES + BODY_ROLES,
                                            mapping=db.feature_joints or None, source=db.path)
        except (InputFileError, ParameterError):
            self._hand_joints = None

    def _stepping(self) -> np.ndarray:
        """Per node: how much more its feet move than the database's typical clip, ``max(0, log(s / median s))``
        with ``s`` the mean horizontal ankle speed over the node's frames (0 for the calmer half).

        The lower body's path is chosen by transition cost alone (Sec. 4.1), which happily walks: on the
        held-out BEAT2 stretch it took the recording's first 16 s, where the speaker steps about, and
        the feet moved 1.8-1.9x as fast as the capture's. This term, weighted like the duration term,
        keeps the stance of a speaker who mostly stands unless the transitions say otherwise.
        """

        feet = foot_joints(self.db.skeleton)[:, 0]
        if feet.size == 0 or self.start.size == 0:
            return np.zeros(self.start.size)
        # every clip's frames (at least two), one read per ankle: Database.rows reads runs of frames
        n = np.maximum(self.length, 2)
        frames = np.minimum(np.concatenate([a + np.arange(k) for a, k in zip(self.start, n)]), self.db.n_frames - 1)
        p = np.stack([np.asarray(self.db.rows("joint_positions", frames, column=int(j)), dtype=np.float64)[:, [0, 2]]
                      for j in feet], axis=1)  # (n_frames, 2, 2)
        step = np.linalg.norm(np.diff(p, axis=0), axis=-1).mean(axis=1) * self.db.fps  # (n_frames - 1,)
        # the mean over each clip's own steps (none across two clips)
        ends, cs = np.cumsum(n), np.concatenate([[0.0], np.cumsum(step)])
        speeds = (cs[ends - 1] - cs[ends - n]) / (n - 1)
        med = float(np.median(speeds))
        return np.log(np.maximum(speeds / med, 1.0)) if med > 0 else np.zeros(self.start.size)

    # -- input side -----------------------------------------------------------
    def input_clips(self, samples, sr, T, *, transcript=None, gap_s=None, vad=DEFAULT_VAD):
        """Input clip boundaries (n+1,) in frames, word onsets (s), and words per clip (n,)."""

        fps = self.db.fps
        if gap_s is not None and gap_s != "auto":
            try:
                ok = float(gap_s) > 0
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise ParameterError(f"gap_s: expected a positive number of seconds or 'auto', got {gap_s!r}")
        if transcript is not None:
            # Words come checked (synthesize read them); a file is read and checked here
            words = transcript if isinstance(transcript, Words) else inputs.read_words(transcript, samples.shape[0] / sr)
            ws, we = np.asarray(words.start_s, float), np.asarray(words.end_s, float)
        else:
            ws, we = voiced_segments(samples, sr, method=vad)
        order = np.argsort(ws, kind="stable")
        ws, we = ws[order], we[order]
        if gap_s == "auto":  # from this speech's own pauses, clips of about 3 s (as the build's "auto")
            pauses = ws[1:] - np.maximum.accumulate(we)[:-1] if ws.size > 1 else np.zeros(0)
            gap = suggest_gap_s(pauses, T / fps)
        else:
            gap = float(self.db.config.get("gap_s", 0.4)) if gap_s is None else float(gap_s)
        self.last_gap_s = gap
        clips = word_gap_clips(ws, we, n_frames=T, fps=fps, gap_s=gap)
        bounds = [int(x) for x in clips.start] + [T]
        bounds = _split_long(bounds, ws, we, fps, int(self.length.max()))
        b = np.asarray(bounds, dtype=np.int64)
        n_words = np.histogram(ws * fps, bins=b)[0] if ws.size else np.zeros(len(b) - 1, dtype=np.int64)
        return b, ws, n_words

    def data_terms(self, query, bounds, onsets_s, n_words, *, l5=1.0, l6=0.1, l_dur=0.5, rhythm="chance"):
        """Components of ``C_d`` (n, K) each: style L2, rhythm (``rhythm``: a key of :data:`RHYTHM_TERMS`),
        duration; plus rates and fit flags."""

        fps = self.db.fps
        starts, lens = bounds[:-1], np.diff(bounds)
        style_in = predict_style(self.style_model, clip_audio_inputs(query, starts, lens, n_words))
        rhythm_in = np.atleast_1d(audio_rhythm(onsets_s, start_s=starts / fps, end_s=bounds[1:] / fps))
        g_z = np.linalg.norm(style_in[:, None, :] - self.style[None, :, :], axis=-1)
        g_r = RHYTHM_TERMS[rhythm](rhythm_in[:, None], self.rhythm_motion[None, :]).astype(np.float64)
        ratio = self.length[None, :] / lens[:, None].astype(np.float64)
        speed = np.clip(ratio, 1 / MAX_SPEED, MAX_SPEED)
        need = np.ceil((lens[:, None] - 1) * speed).astype(np.int64) + 1
        unfit = need > self.avail[None, :]
        dur = np.abs(np.log(ratio))
        unary = l5 * g_z + l6 * g_r + l_dur * dur + UNFIT_PENALTY * unfit
        return unary, dict(style=g_z, rhythm=g_r, duration=dur, speed=speed, unfit=unfit,
                           style_in=style_in, rhythm_in=rhythm_in)

    # -- synthesis ------------------------------------------------------------
    def synthesize(self, audio, *, sr=None, transcript=None, options: "GraphOptions | None" = None,
                   **changes) -> SynthResult:
        """Synthesize gestures for speech by the best path through the motion graph.

        Parameters
        ----------
        audio : path or ndarray [shape=(n,)]
            At least :data:`gesturedb.synth.inputs.MIN_SPEECH_S` long.
        transcript : path, Words or None
            Word timings; without them pauses come from :func:`voiced_segments`.
        options : GraphOptions, optional
            ``gap_s``, ``vad``, ``w_data``, ``w_trans``, ``l5``, ``l6``, ``l_dur``, ``rhythm`` and the
            options every method shares (``seam_decay_s``, ``smooth``, ``control``,
            ``keywords``, ``exclude``, ``speaker``); see :class:`GraphOptions`.
        **changes
            Any of those fields as keywords, over ``options``.

        Returns
        -------
        SynthResult
            ``steps[i]`` per target clip: ``out_start``/``out_end``, ``node``, ``recording``,
            ``source_start_s``/``source_end_s``, ``speed`` (warp rate), ``style_cost``,
            ``rhythm_cost``, ``duration_cost``, ``data_cost``, ``transition_cost`` (into it),
            ``control``, ``keyword``.
        """
        opts = GraphOptions.of(options, **changes)
        if opts.rhythm not in RHYTHM_TERMS:
            raise ParameterError(f"rhythm: expected one of {', '.join(RHYTHM_TERMS)}; got {opts.rhythm!r}")
        gap_s, vad, w_data, w_trans = opts.gap_s, opts.vad, opts.w_data, opts.w_trans
        l5, l6, l_dur, smooth = opts.l5, opts.l6, opts.l_dur, opts.smooth
        control, keywords = opts.control, opts.keywords
        db = self.db
        samples, sr, audio_path = inputs.speech_samples(db, audio, sr)
        seam_decay_s = check_decay_s(opts.seam_decay_s)
        transcript = inputs.read_words(transcript, samples.shape[0] / sr, audio=audio_path)
        inputs.check_speech(samples.shape[0], sr, db.fps, audio=audio_path)
        query = inputs.query_features(db, samples, sr)
        T = query.shape[0]
        bounds, onsets, n_words = self.input_clips(samples, sr, T, transcript=transcript, gap_s=gap_s, vad=vad)
        unary, terms = self.data_terms(query, bounds, onsets, n_words, l5=l5, l6=l6, l_dur=l_dur, rhythm=opts.rhythm)
        excl = inputs.excluded(db, self.recording, opts.exclude, opts.speaker)  # bool per node
        labels, kw_ok = self._apply_masks(unary, bounds, T, control=control, transcript=transcript,
                                          keywords=keywords, exclude=excl)
        path, total = viterbi(unary, *self.upper_graph, w_data=w_data, w_trans=w_trans)
        for i, ok in enumerate(kw_ok):
            if ok is not None and not ok[path[i]]:  # no path through a node with the keyword: say so
                labels[i] = (labels[i][0], labels[i][1] + " (no node)")
        # the lower body's own path (module doc): duration term, plus the penalty where the node's
        # recording ends before the clip does (it plays at its own speed); excluded recordings stay
        # out; controls and keywords are about the arms and do not restrict it
        lens = np.diff(bounds)
        unary_low = (l_dur * (terms["duration"] + self.stepping[None, :])
                     + UNFIT_PENALTY * (lens[:, None] > self.avail[None, :]))
        if excl is not None:
            unary_low[:, excl] = np.inf
        path_low, total_low = viterbi(unary_low, *self.lower_graph, w_data=w_data, w_trans=w_trans)
        motion, source, steps, cuts = self._assemble(path, path_low, bounds, terms, unary, unary_low, labels,
                                               seam_decay_s=seam_decay_s, smooth=smooth)
        options = dict(method="graph", gap_s=self.last_gap_s, w_data=w_data, w_trans=w_trans, l5=l5, l6=l6, l_dur=l_dur,
                       rhythm=opts.rhythm, seam_decay_s=seam_decay_s, smooth=smooth, total_cost=total, total_cost_lower=total_low,
                       control=control if isinstance(control, (str, type(None))) else str(control),
                       keywords=keywords if isinstance(keywords, bool) else list(keywords),
                       transcript=transcript is not None, vad=None if transcript is not None else vad,
                       database=db.path, **({"speaker": opts.speaker} if opts.speaker is not None else {}))
        # every seam: the clips' and the cuts that fitted a longer clip (fit_times)
        seams = np.union1d(bounds[1:-1], np.asarray(cuts, dtype=np.int64))
        return SynthResult(motion=motion, source_frames=source, boundaries=seams, steps=steps,
                           fps=db.fps, audio_path=audio_path, options=options)

    def _apply_masks(self, unary, bounds, T, *, control, transcript, keywords, exclude):
        """Set ``+inf`` where a control/keyword mask or an excluded recording forbids a node; labels per clip.

        Control: node ``d`` is allowed for clip ``i`` when at least half of its frames are in the
        mask active at ``i``'s middle frame. Keywords: a clip whose speech contains a keyword of a
        keyword sub-database is filled by a node that overlaps one of the speaker's own
        occurrences of that keyword (a frame of its sub-database) wherever the graph's edges allow
        it: the other nodes cost ``KEYWORD_MISS_PENALTY`` more (a penalty, not a mask: on a small
        graph two keyword clips in a row can leave no edge between allowed nodes). A clip is a
        phrase, so the keyword decides which phrase, not where in it the gesture falls.

        ``exclude``: bool per node (:func:`gesturedb.synth.inputs.excluded`) or None.
        Returns the labels per clip and, per clip, the bool array of nodes that overlap one of
        its keywords (None for a clip without keyword).
        """
        n = unary.shape[0]
        labels = [None] * n
        if exclude is not None:
            unary[:, exclude] = np.inf
        F = self.db.n_frames

        def node_frames_in(bits):
            """Frames of every node inside a packed bitset (n_nodes,)."""
            on = np.unpackbits(np.ascontiguousarray(bits).view(np.uint8), bitorder="little")[:F]
            cs = np.concatenate([[0], np.cumsum(on, dtype=np.int64)])
            return cs[self.start + self.length] - cs[self.start]

        ctl_labels = [None] * n
        if control:
            allowed, lab, _ = inputs.step_masks(self.db, control, None, False, n_steps=T, step=1, T=T)
            if allowed is not None:
                mid = (bounds[:-1] + bounds[1:]) // 2
                for i, t in enumerate(mid):
                    unary[i, 2 * node_frames_in(allowed[int(t)]) < self.length] = np.inf
                    ctl_labels[i] = lab[int(t)][0] if lab is not None and lab[int(t)] else None
        kw_labels = [None] * n
        kw_ok = [None] * n
        if keywords and transcript is not None:
            _, lab, bits = inputs.step_masks(self.db, None, transcript, keywords, n_steps=T, step=1, T=T)
            if bits is not None:
                word = [x[1] if x else None for x in lab]  # the keyword said at each output frame
                for i in range(n):
                    frames = [t for t in range(int(bounds[i]), int(bounds[i + 1])) if word[t] is not None]
                    if not frames:
                        continue
                    union = np.bitwise_or.reduce(np.asarray(bits)[frames], axis=0)
                    kw_ok[i] = node_frames_in(union) > 0
                    unary[i, ~kw_ok[i]] += KEYWORD_MISS_PENALTY
                    kw_labels[i] = ", ".join(dict.fromkeys(word[t] for t in frames))
        for i in range(n):
            if ctl_labels[i] is not None or kw_labels[i] is not None:
                labels[i] = (ctl_labels[i], kw_labels[i])
        return labels, kw_ok

    def _pieces(self, path, bounds, speeds, seam_decay_s):
        """The fitted source pieces of a path (:func:`fit_times`), their source frames (T,), the source times per
        clip and the output frames where a clip resumes after a cut.

        ``speeds``: (n, K) warp rate of node ``d`` for clip ``i``, or None for the source speed.
        """

        db = self.db
        pieces, times = [], []
        source = np.empty(int(bounds[-1]), dtype=np.int64)
        prev = None  # (time of the previous piece's last frame, its speed, its recording's last frame)
        cuts = []  # output frames where a clip resumes after a cut (fit_times)

        def warped(t, lo, hi):
            """Source motion at fractional frames t, held at frames lo and hi (its recording's ends).

            Catmull-Rom between the four nearest frames (quaternions on one hemisphere, then
            normalised): a slerp between the two nearest halves the power of a 3 Hz stroke played
            at 0.8x (at 15 fps, held out: arm velocity power 0.48 -> 0.22 of the database's at 2-4 Hz).
            """
            f = np.floor(t).astype(np.int64)
            u = (t - f)[:, None]
            idx = np.clip(f[:, None] + np.arange(-1, 3)[None, :], lo, hi)  # (n, 4)
            rr, pp = placed_frames(db, idx.ravel())
            rr = rr.reshape(idx.shape + rr.shape[1:])  # (n, 4, J, 4)
            pp = pp.reshape(idx.shape + (3,))
            # the four samples on the hemisphere of the second (q and -q are one rotation)
            rr = np.where((rr * rr[:, 1:2]).sum(-1, keepdims=True) < 0, -rr, rr)
            w = np.concatenate([-0.5 * u ** 3 + u ** 2 - 0.5 * u, 1.5 * u ** 3 - 2.5 * u ** 2 + 1,
                                -1.5 * u ** 3 + 2 * u ** 2 + 0.5 * u, 0.5 * u ** 3 - 0.5 * u ** 2], axis=1)  # (n, 4)
            q = np.einsum("nk,nkjc->njc", w, rr)
            return q / np.linalg.norm(q, axis=-1, keepdims=True), np.einsum("nk,nkc->nc", w, pp)

        for i, d in enumerate(path):
            a, b = int(bounds[i]), int(bounds[i + 1])
            L = b - a
            speed = 1.0 if speeds is None else float(speeds[i, d])
            hi = self.start[d] + self.avail[d] - 1  # hold the recording's last frame if it runs out
            lo = int(self.rec_start[d])
            # a piece played as it is (the lower body's) needs no hand speed: no read for it
            hand = self._hand_speed(int(d), int(np.ceil((L - 1) * speed)) + 1) if speed != 1.0 else np.zeros(0)
            rel, fit_cuts = fit_times(hand, L, speed, fps=db.fps)
            t = self.start[d] + rel
            rot, root = warped(t, lo, hi)
            # the parts after the cuts, each with the seam from how the part before it goes on
            rests = [Piece(out_start=a + c, rotations=rot[c:e], root=root[c:e],
                           lead_in=warped(t[c - 1] + np.arange(1, LEAD_FRAMES + 1), lo, hi))
                     for c, e in zip(fit_cuts, fit_cuts[1:] + [L])]
            if fit_cuts:
                rot, root = rot[:fit_cuts[0]], root[:fit_cuts[0]]
                cuts += [a + c for c in fit_cuts]
            lead = None
            if prev is not None and seam_decay_s > 0:
                # how the previous piece goes on: its own recording, at its own warp rate, from the time
                # after its last frame (the next source frame would skip or repeat part of a frame)
                t_prev, s_prev, hi_prev, lo_prev = prev  # s_prev: the rate of its last frame
                tl = t_prev + s_prev * np.arange(1, LEAD_FRAMES + 1)
                tl = tl[tl <= hi_prev]
                if tl.size:
                    lead = warped(tl, lo_prev, hi_prev)
            pieces.append(Piece(out_start=a, rotations=rot, root=root, lead_in=lead))
            pieces += rests
            source[a:b] = np.rint(t).astype(np.int64).clip(max=hi)
            last_rate = float(t[-1] - t[-2]) if L > 1 else speed
            prev = (float(t[-1]), last_rate, int(self.start[d] + self.avail[d] - 1) if t[-1] <= hi else -1, lo)
            times.append(t)
        return pieces, source, times, cuts

    def _hand_speed(self, d: int, m: int) -> np.ndarray:
        """Hand speed (m/s, :func:`gesturedb.features.rhythm.hand_speed`) of node ``d``'s first ``m`` source
        frames (fewer where its recording ends), from a few frames of context on either side."""
        db = self.db
        if self._hand_joints is None:
            return np.zeros(0)
        pad = max(2, int(np.ceil(0.2 * db.fps)))  # the speed's smoothing and differences need context
        a0, end = int(self.start[d]), int(self.start[d] + self.avail[d])
        lo, hi = max(int(self.rec_start[d]), a0 - pad), min(end, a0 + m + pad)
        if hi - lo < 3:
            return np.zeros(0)
        pos = np.asarray(db.rows("joint_positions", np.arange(lo, hi)), dtype=np.float64)
        return hand_speed(pos, joints=self._hand_joints, fps=db.fps)[a0 - lo: min(a0 + m, end) - lo]

    def _edge(self, graph, p, q):
        indptr, indices, cost = graph
        row = indices[indptr[p]:indptr[p + 1]]
        return float(cost[indptr[p] + np.searchsorted(row, q)])

    def _assemble(self, path, path_low, bounds, terms, unary, unary_low, labels, *, seam_decay_s, smooth):
        """Upper body from ``path``, root and legs from ``path_low``, joined into one motion (Sec. 4.2).

        Each path's pieces go through :func:`assemble_pieces` (placement, seam cross-fades; feet
        planted on the lower body's); the result takes the local rotations of the upper-body
        joints from the first and the root and the legs from the second: the upper body rides on
        the lower body's pelvis.
        """

        db = self.db
        recs = db.recordings
        T = int(bounds[-1])
        up_pieces, source, up_t, cuts = self._pieces(path, bounds, terms["speed"], seam_decay_s)
        low_pieces, _, low_t, _ = self._pieces(path_low, bounds, None, seam_decay_s)
        accel = typical_accelerations(db) if seam_decay_s > 0 else None
        upper = assemble_pieces(db.skeleton, db.fps, up_pieces, n_frames=T, seam_decay_s=seam_decay_s, smooth=False,
                                lock_feet=False, seam_accel=accel)  # its legs are dropped
        lower = assemble_pieces(db.skeleton, db.fps, low_pieces, n_frames=T, seam_decay_s=seam_decay_s, smooth=False,
                                seam_accel=accel, floor_y=floor_height(db))
        rot = np.array(lower.rotations, dtype=np.float64, copy=True)
        rot[:, self.upper_joints] = upper.rotations[:, self.upper_joints]
        rot = join_upper_body(db.skeleton, rot, upper.rotations, self.upper_joints)
        motion = Motion(skeleton=db.skeleton, fps=db.fps, rotations=rot, root_positions=lower.root_positions)

        def where(d, t):
            rec = recs[int(self.recording[d])]
            return rec.name, round((float(t[0]) - rec.start_frame) / db.fps, 4), \
                round((float(t[-1]) + 1 - rec.start_frame) / db.fps, 4)

        steps = []
        for i, (d, e) in enumerate(zip(path, path_low)):
            a, b = int(bounds[i]), int(bounds[i + 1])
            name, s0, s1 = where(d, up_t[i])
            lname, l0, l1 = where(e, low_t[i])
            lab = labels[i]
            steps.append({
                "step": i, "out_start": a, "out_end": b, "time_s": round(a / db.fps, 4),
                "node": int(d), "recording": name, "source_start_s": s0, "source_end_s": s1,
                "speed": round(float(terms["speed"][i, d]), 4),
                "style_cost": float(terms["style"][i, d]), "rhythm_cost": float(terms["rhythm"][i, d]),
                "duration_cost": float(terms["duration"][i, d]), "unfit": bool(terms["unfit"][i, d]),
                "data_cost": float(unary[i, d]),
                "transition_cost": self._edge(self.upper_graph, int(path[i - 1]), int(d)) if i else None,
                "control": lab[0] if lab else None, "keyword": lab[1] if lab else None,
                "lower": {"node": int(e), "recording": lname, "source_start_s": l0, "source_end_s": l1,
                          "speed": 1.0, "data_cost": float(unary_low[i, e]),
                          "transition_cost": self._edge(self.lower_graph, int(path_low[i - 1]), int(e)) if i else None},
            })
        if smooth:
            motion = self._smooth(motion)
        return motion, source, steps, cuts

    def _smooth(self, motion):
        """Savitzky-Golay per joint group (Sec. 4.2): order 2 for arms/hands/head, 1 elsewhere; window in seconds."""

        names = motion.skeleton.names
        o2 = np.array([any(k in nm.lower() for k in ORDER2_PARTS) for nm in names])
        rot = np.array(motion.rotations, dtype=np.float64)
        root = np.array(motion.root_positions, dtype=np.float64)
        r2, _ = savgol_smooth(rot[:, o2], root, fps=motion.fps, window_s=SMOOTH_WINDOW_S, order=2)
        r1, root1 = savgol_smooth(rot[:, ~o2], root, fps=motion.fps, window_s=SMOOTH_WINDOW_S, order=1)
        rot[:, o2], rot[:, ~o2] = r2, r1
        return Motion(skeleton=motion.skeleton, fps=motion.fps, rotations=rot, root_positions=root1)


#: The motion-graph method in the registry (:mod:`gesturedb.synth.methods`).
METHOD = Method(
    name="graph",
    summary="GestureMaster motion-graph path search (Zhou et al. 2022); plans over whole phrases, so it does not stream",
    options=GraphOptions,
    open=GraphSynthesizer,
    systems=(EvalSystem("graph", "motion graph (GestureMaster)", "#8c564b"),),
)
