"""Build a gesture database: recordings -> features -> segments -> HDF5.

A recording is a motion file (BVH or SMPL-X npz), a speech WAV and, optionally, a
transcript (TextGrid, GENEA TSV or JSON) that share a file stem. Each recording
is processed on its own (in worker processes when ``workers > 1``); its per-frame
arrays are appended to the file in input order as it arrives
(:mod:`gesturedb.db.framewriter`, which then standardises the audio features with
statistics of the whole database), and everything is written through
:mod:`gesturedb.db.schema` into a temporary file beside the target that is renamed
on success. A failed or interrupted build leaves no partial file and any
existing database untouched; the same inputs and configuration give the same
HDF5 content.
"""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from gesturedb import control
from gesturedb._version import __version__
from gesturedb.db import schema, store
from gesturedb.db.cluster import check_on_worker, check_scheduler, iter_on_cluster, optional_client
from gesturedb.db.database import Database
from gesturedb.db.framewriter import FrameWriter
from gesturedb.db.graph import suggest_gap_s, write_graph
from gesturedb.db.storage import check_writes, write_atomically
from gesturedb.db.takes import (  # noqa: F401  (re-exported: build is where callers look)
    MIRROR_NOTE_REL,
    PAIRING_COLUMNS,
    RecordingSource,
    infer_speaker,
    mirrored_copy,
    read_pairing_file,
)
from gesturedb.db.workers import single_threaded_worker
from gesturedb.errors import InputFileError, ParameterError
from gesturedb.features import controls as fcontrols
from gesturedb.features import pose as fpose
from gesturedb.features import rhythm as frhythm
from gesturedb.features import segments as fseg
from gesturedb.features import style as fstyle
from gesturedb.features.audio import audio_features
from gesturedb.features.pauses import DEFAULT_VAD, VAD_METHODS, voiced_segments
from gesturedb.io import read_audio, read_motion, read_transcript
from gesturedb.io.audio import audio_duration
from gesturedb.io.bvh import describe_length_unit
from gesturedb.io.joints import BODY_ROLES, FEATURE_ROLES, ankle_joints, find_joints
from gesturedb.io.outputs import check_outputs
from gesturedb.io.transcripts import Words

MOTION_EXTS = (".bvh", ".npz")
AUDIO_EXTS = (".wav", ".flac")
TRANSCRIPT_EXTS = (".textgrid", ".tsv", ".json")


# --------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------

@dataclass(frozen=True)
class BuildConfig:
    """Everything that determines the content of a database.

    Attributes
    ----------
    fps : float
        Database frame rate (Hz); 15 as in Habibie et al. 2022.
    chunk_frames : int or None
        Length of the fixed chunks, frames; None (default): the paper's T_match = 64 frames at
        15 fps, kept in seconds (:data:`gesturedb.features.segments.CHUNK_S`: 128 at 30 fps).
    gap_s : float or "auto"
        Word-gap clips split where the pause between words exceeds this (s). ``"auto"``
        (default): chosen from the recordings' own pauses so that clips last about 3 s
        (:func:`gesturedb.db.graph.suggest_gap_s`, at most GestureMaster's 0.4 s: Sec. 3.1 ties
        the threshold to the speaker's speech rate and aims at clips of a few seconds); the
        number chosen is what the file stores.
    pose_window : int
        Pose feature = feature joints at frames f + k * stride for k = -(window-1) .. window-1
        (:func:`gesturedb.features.pose.pose_features`).
    pose_stride : int or None
        Frames between them; None (default): from the recordings' own motion, once they are all
        in (:func:`gesturedb.features.pose.timescale_pose_stride` of the whole database's
        :func:`gesturedb.features.pose.motion_timescale`: 2 at 15 fps and 4 at 30 fps for the
        BEAT2 speaker, fewer for one who moves faster). The file's ``config`` records the number.
    sample_rate : int
        Analysis rate for speech (Hz).
    n_mfcc : int
        MFCC coefficients (13) + log mean energy.
    mirror : bool
        Also add a left/right mirrored copy of every recording (doubles the database).
    joint_map : dict or None
        role -> joint name, overriding the name matching (see :mod:`gesturedb.io.joints`).
    max_mismatch_s : float
        Largest allowed difference between audio and motion durations (s).
    speaker : str or None
        Speaker name for every recording that does not name its own (a pairing
        file's ``speaker`` column); None infers it (:func:`infer_speaker`).
    length_unit_m : float or None
        Metres per length unit of the BVH files; None guesses it per file from
        the skeleton's height (:func:`gesturedb.io.bvh.guess_length_unit`) and
        the build report says what was guessed.
    graph : bool
        Also build the motion graph and style predictor (:mod:`gesturedb.db.graph`).
    vad : "silero" or "energy"
        How a recording without a transcript is cut at its pauses
        (:func:`gesturedb.features.pauses.voiced_segments`); the same detector as the graph
        synthesis's default, so database and input clips are cut alike.
    """

    fps: float = 15.0
    chunk_frames: int | None = None
    gap_s: float | str = "auto"
    pose_window: int = fpose.POSE_WINDOW
    pose_stride: int | None = None
    sample_rate: int = schema.DEFAULT_SAMPLE_RATE
    n_mfcc: int = 13
    mirror: bool = False
    joint_map: dict | None = None
    max_mismatch_s: float = 1.0
    speaker: str | None = None
    graph: bool = True
    length_unit_m: float | None = None
    vad: str = DEFAULT_VAD

    def __post_init__(self):
        def bad(name, expected):
            raise ParameterError(f"{name}: expected {expected}, got {getattr(self, name)!r}")

        if not (np.isfinite(self.fps) and self.fps > 0):
            bad("fps", "a positive number of frames per second")
        # lengths in frames that the paper gives at 15 fps: kept in seconds at any frame rate
        if self.chunk_frames is None:
            object.__setattr__(self, "chunk_frames", fseg.default_chunk_frames(self.fps))
        for name in ("chunk_frames", "pose_window", "pose_stride", "sample_rate", "n_mfcc"):
            v = getattr(self, name)
            if name == "pose_stride" and v is None:
                continue  # chosen from the data once every recording is in (build)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                bad(name, "a positive integer")
        if self.gap_s != "auto" and not (isinstance(self.gap_s, (int, float)) and self.gap_s > 0):
            bad("gap_s", "a positive number of seconds")
        if self.vad not in VAD_METHODS:
            bad("vad", "one of " + ", ".join(VAD_METHODS))
        if not (self.max_mismatch_s >= 0):
            bad("max_mismatch_s", "a non-negative number of seconds")
        if self.joint_map is not None and not isinstance(self.joint_map, dict):
            bad("joint_map", "a dict role -> joint name")
        if self.length_unit_m is not None and (isinstance(self.length_unit_m, bool) or not isinstance(
                self.length_unit_m, (int, float)) or not (np.isfinite(self.length_unit_m) and self.length_unit_m > 0)):
            bad("length_unit_m", "a positive number of metres per BVH length unit or None (guessed)")

    @classmethod
    def from_kwargs(cls, **config) -> "BuildConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(config) - names)
        if unknown:
            raise ParameterError(f"build option(s) {unknown}: not known; options are {sorted(names)}")
        return cls(**config)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["fps"] = float(d["fps"])
        return d


# --------------------------------------------------------------------------
# pairing input files
# --------------------------------------------------------------------------

@dataclass(frozen=True)
class Skipped:
    path: str
    reason: str


@dataclass
class Pairing:
    recordings: list[RecordingSource] = field(default_factory=list)
    skipped: list[Skipped] = field(default_factory=list)
    #: lines of the build report written while processing (unit guessed, skeleton sides that differ)
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        lines = [f"paired {len(self.recordings)} recording(s):"]
        for r in self.recordings:
            t = os.path.basename(r.transcript) if r.transcript else "no transcript: clips cut at the pauses of the speech"
            who = f" (speaker {r.speaker})" if r.speaker else ""
            lines.append(f"  {r.name}: {os.path.basename(r.motion)} + {os.path.basename(r.audio)} + {t}{who}")
        if self.skipped:
            lines.append(f"skipped {len(self.skipped)} file(s):")
            lines += [f"  {s.path}: {s.reason}" for s in self.skipped]
        return "\n".join(lines)


def _kind(path: Path) -> str | None:
    ext = path.suffix.lower()
    if ext in MOTION_EXTS:
        return "motion"
    if ext in AUDIO_EXTS:
        return "audio"
    if ext in TRANSCRIPT_EXTS:
        return "transcript"
    return None


def pair_inputs(inputs: Iterable[str | os.PathLike], *, recursive: bool = False) -> Pairing:
    """Pair motion, audio and transcript files by stem.

    Parameters
    ----------
    inputs : iterable of paths
        Files and folders. Folders contribute the files directly inside them
        (and below them with ``recursive=True``).

    Returns
    -------
    Pairing
        The recordings, sorted by name, and every file that was skipped with the reason.
    """
    files: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            it = p.rglob("*") if recursive else p.iterdir()
            files += sorted(q for q in it if q.is_file())
        elif p.is_file():
            files.append(p)
        else:
            raise InputFileError(p, "no such file or folder")

    out = Pairing()
    by_stem: dict[tuple[str, str], dict[str, list[Path]]] = {}
    for f in files:
        kind = _kind(f)
        if kind is None:
            if f.name.startswith(".") or f.suffix.lower() in (".md", ".txt"):
                continue
            out.skipped.append(Skipped(str(f), f"extension {f.suffix!r} is not motion {MOTION_EXTS}, audio {AUDIO_EXTS} or transcript {TRANSCRIPT_EXTS}"))
            continue
        # pair within a folder: the same stem in two folders is two recordings
        by_stem.setdefault((str(f.parent), f.stem), {}).setdefault(kind, []).append(f)

    names_seen: dict[str, str] = {}
    for (folder, stem), kinds in sorted(by_stem.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        all_files = [str(p) for ps in kinds.values() for p in ps]
        dup = [k for k, ps in kinds.items() if len(ps) > 1]
        if dup:
            for p in all_files:
                out.skipped.append(Skipped(p, f"stem {stem!r} has several {dup[0]} files ({', '.join(os.path.basename(q) for q in sorted(map(str, kinds[dup[0]])))}): ambiguous"))
            continue
        if "motion" not in kinds:
            for p in all_files:
                out.skipped.append(Skipped(p, f"no motion file ({'/'.join(MOTION_EXTS)}) with stem {stem!r}"))
            continue
        if "audio" not in kinds:
            for p in all_files:
                out.skipped.append(Skipped(p, f"no audio file ({'/'.join(AUDIO_EXTS)}) with stem {stem!r}"))
            continue
        if stem in names_seen:
            for p in all_files:
                out.skipped.append(Skipped(p, f"a recording named {stem!r} was already paired from {names_seen[stem]}"))
            continue
        names_seen[stem] = folder
        tr = kinds.get("transcript")
        out.recordings.append(
            RecordingSource(stem, str(kinds["motion"][0]), str(kinds["audio"][0]), str(tr[0]) if tr else None)
        )
    return out


# --------------------------------------------------------------------------
# one recording
# --------------------------------------------------------------------------

@dataclass
class RecordingData:
    """Everything computed from one recording (frame indices local to it)."""

    name: str
    speaker: str
    source: RecordingSource
    source_fps: float
    mirrored: bool
    n_frames: int
    skeleton: object
    feature_joints: dict
    pose: np.ndarray | None     # (n, Dp) float32; None: computed once the stride is known (build)
    velocity_lags: np.ndarray   # (L + 1,) float64: features.pose.velocity_lag_products
    audio_raw: np.ndarray       # (n, Da) float32, before standardisation
    positions: np.ndarray       # (n, J, 3)
    rotations: np.ndarray       # (n, J, 4)
    root: np.ndarray            # (n, 3)
    controls: dict
    chunks: tuple               # (start, length) local
    clips: dict                 # start, length, word_start, word_end (local), rhythm_audio, rhythm_motion, style
    words: tuple                # (start_s, end_s, text)
    notes: list = field(default_factory=list)  # (topic, file name, text) for the build report


def _check_finite(path: str, what: str, arr: np.ndarray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        idx = np.argwhere(bad)[0]
        raise InputFileError(path, f"{what}: expected finite values, got {arr[tuple(idx)]} at index {tuple(int(i) for i in idx)}")


def _features_for(motion, audio_raw, words, cfg: BuildConfig, source: RecordingSource, *,
                  mirrored: bool, source_fps: float) -> RecordingData:
    """Features, segments and signatures of one (possibly mirrored) motion with its audio features."""

    joints = find_joints(motion.skeleton.names, FEATURE_ROLES + BODY_ROLES, mapping=cfg.joint_map, source=source.motion)
    positions = motion.positions
    n = positions.shape[0]
    _check_finite(source.motion, "joint positions", positions)

    # features from the positions exactly as stored (float32), so that recomputing them from the file
    # (`gesturedb upgrade`, tests) gives the same bits
    positions32 = positions.astype(np.float32).astype(np.float64)
    pose = None if cfg.pose_stride is None else fpose.pose_features(
        positions32, joints=joints, fps=cfg.fps, window=cfg.pose_window, stride=cfg.pose_stride,
        stance=ankle_joints(motion.skeleton.names))
    lags = fpose.velocity_lag_products(positions32, joints=joints, fps=cfg.fps)
    controls = fcontrols.control_features(positions32, joints=joints, fps=cfg.fps)

    c_start, c_len = fseg.fixed_chunks(n, length=cfg.chunk_frames)
    w_start = np.asarray(words.start_s if words is not None else [], dtype=np.float64)
    w_end = np.asarray(words.end_s if words is not None else [], dtype=np.float64)
    clips = fseg.word_gap_clips(w_start, w_end, n_frames=n, fps=cfg.fps, gap_s=cfg.gap_s)
    speed = frhythm.hand_speed(positions, joints=joints, fps=cfg.fps)
    # clips tile the recording, so the onsets inside a clip's span are exactly its words
    rh_audio = np.atleast_1d(frhythm.audio_rhythm(
        w_start, start_s=clips.start / cfg.fps, end_s=(clips.start + clips.length) / cfg.fps)).astype(np.uint32)
    rh_motion = np.atleast_1d(frhythm.motion_rhythm(
        speed, start=clips.start, length=clips.length, fps=cfg.fps)).astype(np.uint32)
    style = fstyle.style_signatures(positions, joints=joints, fps=cfg.fps, starts=clips.start, lengths=clips.length)

    name = source.name + ("~mirror" if mirrored else "")
    return RecordingData(
        name=name,
        speaker=source.speaker or cfg.speaker or infer_speaker(source),
        source=source,
        source_fps=source_fps,
        mirrored=mirrored,
        n_frames=n,
        skeleton=motion.skeleton,
        feature_joints={r: motion.skeleton.names[i] for r, i in joints.items()},
        pose=pose,
        velocity_lags=lags,
        audio_raw=audio_raw,
        positions=positions.astype(np.float32),
        rotations=motion.rotations.astype(np.float32),
        root=motion.root_positions.astype(np.float32),
        controls=controls,
        chunks=(c_start, c_len),
        clips=dict(start=clips.start, length=clips.length, word_start=clips.word_start, word_end=clips.word_end,
                   rhythm_audio=rh_audio, rhythm_motion=rh_motion, style=style),
        words=(w_start, w_end, list(words.text) if words is not None else []),
    )


def process_recording(source: RecordingSource, cfg: BuildConfig, words=None) -> list[RecordingData]:
    """Read one recording and compute all its features (and its mirrored copy).

    ``words``: the recording's transcript as :func:`gesturedb.io.read_transcript` returns it,
    when the caller has read it already (the automatic gap reads every transcript first: passing
    them on spares each recording a second parse, about a tenth of its processing time); None:
    read here.

    Raises :class:`InputFileError` naming the file and field for bad input:
    unreadable or truncated files, NaN, audio and motion durations that differ by
    more than ``cfg.max_mismatch_s``.
    """

    is_bvh = Path(source.motion).suffix.lower() == ".bvh"
    motion = read_motion(source.motion, length_unit_m=cfg.length_unit_m if is_bvh else None)
    notes = []
    if is_bvh:
        how = "guessed" if cfg.length_unit_m is None else "given"
        notes.append(("unit", os.path.basename(source.motion), f"{how} {describe_length_unit(motion.skeleton)}"
                      + ("; --length-unit overrides" if cfg.length_unit_m is None else "")))
    src_fps = float(motion.fps)
    if not 1.0 <= src_fps <= 1000.0:
        raise InputFileError(source.motion, f"frame rate: expected 1 to 1000 fps, got {src_fps:.6g}")
    motion_dur = motion.rotations.shape[0] / src_fps
    samples, sr = read_audio(source.audio, sr=cfg.sample_rate)
    audio_dur = samples.shape[0] / sr
    if abs(audio_dur - motion_dur) > cfg.max_mismatch_s:
        raise InputFileError(
            source.audio,
            f"duration: expected within {cfg.max_mismatch_s:g} s of the motion "
            f"({motion_dur:.2f} s in {os.path.basename(source.motion)}), got {audio_dur:.2f} s",
        )
    if words is None and source.transcript:
        words = read_transcript(source.transcript)
    if words is None:
        # no transcript: voiced stretches of the speech stand in for words (empty text), so the
        # recording is still cut into clips at its pauses, as the graph synthesis cuts its input
        vs, ve = voiced_segments(samples, sr, method=cfg.vad)
        words = Words(start_s=vs, end_s=ve, text=[""] * len(vs), source=None)
    if source.span_s is not None:
        motion, samples, words, motion_dur = _trim(source, motion, samples, sr, words)
    if words is not None and len(words):
        keep = np.asarray(words.start_s) < motion_dur
        if not keep.all():
            words = words[: int(keep.sum())]

    motion = motion.resample(cfg.fps)
    # one audio analysis serves the recording and its mirrored copy
    audio_raw = audio_features(samples, sr, fps=cfg.fps, n_frames=motion.n_frames, n_mfcc=cfg.n_mfcc)
    _check_finite(source.audio, "audio features", audio_raw)
    out = [_features_for(motion, audio_raw, words, cfg, source, mirrored=False, source_fps=src_fps)]
    out[0].notes += notes
    if cfg.mirror:
        mirrored, note = mirrored_copy(motion, source.motion)
        if note:
            out[0].notes.append(("mirror", os.path.basename(source.motion), note))
        out.append(_features_for(mirrored, audio_raw, words, cfg, source, mirrored=True, source_fps=src_fps))
    return out


def _trim(source: RecordingSource, motion, samples, sr, words):
    """Keep ``source.span_s`` of a recording: motion frames, audio samples and the words that start in it."""
    a_s, b_s = (float(x) for x in source.span_s)
    dur = motion.rotations.shape[0] / motion.fps
    if not (0 <= a_s < b_s <= dur + 1e-6):
        raise ParameterError(f"span_s of {source.name}: expected 0 <= start < end <= {dur:.3f} s, got {source.span_s}")
    fa, fb = int(round(a_s * motion.fps)), min(int(round(b_s * motion.fps)), motion.rotations.shape[0])
    motion = motion[fa:fb]
    samples = samples[int(round(a_s * sr)): int(round(b_s * sr))]
    if words is not None:
        keep = (np.asarray(words.start_s) >= a_s) & (np.asarray(words.start_s) < b_s)
        kept = words[keep]
        words = type(kept)(start_s=kept.start_s - a_s, end_s=np.minimum(kept.end_s, b_s) - a_s,
                           text=kept.text, source=kept.source)
    return motion, samples, words, (fb - fa) / motion.fps


def _process_star(args):
    return process_recording(*args)


def _on_worker_paths(source: RecordingSource) -> RecordingSource:
    """``source`` with absolute paths, for a Dask worker: it may run in another folder."""
    return dataclasses.replace(source, motion=os.path.abspath(source.motion), audio=os.path.abspath(source.audio),
                               transcript=source.transcript and os.path.abspath(source.transcript))


def _process_on_worker(args):
    """:func:`process_recording` on a Dask worker, whose machine must see the input files at the
    paths the client gave (made absolute by the client, see :func:`_on_worker_paths`)."""

    source = args[0]
    for path in (source.motion, source.audio, source.transcript if args[2] is None else None):
        if path:
            check_on_worker(path, "the input files")
    return process_recording(*args)


# --------------------------------------------------------------------------
# assembly and writing
# --------------------------------------------------------------------------

def _same_skeleton(a, b) -> bool:
    return a.same_as(b, atol_m=1e-6) and float(a.length_unit_m) == float(b.length_unit_m)


def _write(h5, recs: list[RecordingData], cfg: BuildConfig, progress: bool, frames: FrameWriter,
           scheduler=None) -> None:
    dims: dict[str, int] = {}
    starts = np.cumsum([0] + [r.n_frames for r in recs])[:-1]
    F = int(sum(r.n_frames for r in recs))
    W = schema.write

    store.set_attrs(h5, "", {"schema_version": schema.SCHEMA_VERSION, "gesturedb_version": __version__,
                             "fps": float(cfg.fps), "n_frames": F})
    schema.write_json_attr(h5, "config", cfg.to_json())
    schema.write_json_attr(h5, "feature_joints", recs[0].feature_joints)

    W(h5, schema.RECORDING_NAME, [r.name for r in recs], dims)
    W(h5, schema.RECORDING_SPEAKER, [r.speaker for r in recs], dims)
    W(h5, schema.RECORDING_MOTION_PATH, [r.source.motion for r in recs], dims)
    W(h5, schema.RECORDING_AUDIO_PATH, [r.source.audio for r in recs], dims)
    W(h5, schema.RECORDING_TRANSCRIPT_PATH, [r.source.transcript or "" for r in recs], dims)
    W(h5, schema.RECORDING_START_FRAME, starts, dims)
    W(h5, schema.RECORDING_N_FRAMES, [r.n_frames for r in recs], dims)
    W(h5, schema.RECORDING_DURATION_S, [r.n_frames / cfg.fps for r in recs], dims)
    W(h5, schema.RECORDING_SOURCE_FPS, [r.source_fps for r in recs], dims)
    W(h5, schema.RECORDING_MIRRORED, [r.mirrored for r in recs], dims)

    # written as the recordings came (build); the audio is standardised now
    mean, std = frames.close(dims)
    W(h5, schema.AUDIO_MEAN, mean, dims)
    W(h5, schema.AUDIO_STD, std, dims)

    sk = recs[0].skeleton
    W(h5, schema.SKELETON_NAMES, sk.names, dims)
    W(h5, schema.SKELETON_PARENTS, np.asarray(sk.parents, dtype=np.int64), dims)
    W(h5, schema.SKELETON_OFFSETS, np.asarray(sk.offsets, dtype=np.float64), dims)
    W(h5, schema.SKELETON_CHANNEL_ORDERS, list(sk.channel_orders), dims)
    ej = sorted(sk.end_sites)
    W(h5, schema.SKELETON_END_SITE_JOINTS, np.asarray(ej, dtype=np.int64), dims)
    W(h5, schema.SKELETON_END_SITE_OFFSETS, np.asarray([sk.end_sites[j] for j in ej], dtype=np.float64).reshape(-1, 3), dims)
    # metres per length unit of the source files, so export writes BVH back in those units
    store.set_attrs(h5, schema.SKELETON, {schema.LENGTH_UNIT_ATTR: float(getattr(sk, "length_unit_m", 1.0))})

    W(h5, schema.CHUNK_START, np.concatenate([r.chunks[0] + s for r, s in zip(recs, starts)]), dims)
    W(h5, schema.CHUNK_LENGTH, np.concatenate([r.chunks[1] for r in recs]), dims)
    W(h5, schema.CHUNK_RECORDING, np.concatenate([np.full(len(r.chunks[0]), i, np.int32) for i, r in enumerate(recs)]), dims)

    word_base = np.cumsum([0] + [len(r.words[0]) for r in recs])[:-1]
    cat = lambda key: np.concatenate([r.clips[key] for r in recs])  # noqa: E731
    W(h5, schema.CLIP_START, np.concatenate([r.clips["start"] + s for r, s in zip(recs, starts)]), dims)
    W(h5, schema.CLIP_LENGTH, cat("length"), dims)
    W(h5, schema.CLIP_RECORDING, np.concatenate([np.full(len(r.clips["start"]), i, np.int32) for i, r in enumerate(recs)]), dims)
    W(h5, schema.CLIP_WORD_START, np.concatenate([r.clips["word_start"] + b for r, b in zip(recs, word_base)]), dims)
    W(h5, schema.CLIP_WORD_END, np.concatenate([r.clips["word_end"] + b for r, b in zip(recs, word_base)]), dims)
    W(h5, schema.CLIP_RHYTHM_AUDIO, cat("rhythm_audio"), dims)
    W(h5, schema.CLIP_RHYTHM_MOTION, cat("rhythm_motion"), dims)
    W(h5, schema.CLIP_STYLE, cat("style").astype(np.float32).reshape(-1, 3), dims)

    W(h5, schema.WORD_RECORDING, np.concatenate([np.full(len(r.words[0]), i, np.int32) for i, r in enumerate(recs)]), dims)
    W(h5, schema.WORD_START_S, np.concatenate([r.words[0] for r in recs]), dims)
    W(h5, schema.WORD_END_S, np.concatenate([r.words[1] for r in recs]), dims)
    W(h5, schema.WORD_TEXT, [t for r in recs for t in r.words[2]], dims)

    check_writes(h5)
    write_default_masks(h5, frames.controls)
    if cfg.graph:
        check_writes(h5)  # before the graph's edge search, which takes minutes on a large database
        write_graph(h5, progress=bool(progress), scheduler=scheduler)


def write_default_masks(h5, controls) -> None:
    """Precompute the 15th/85th-percentile masks of every control feature (Habibie et al. Sec. 4.1).

    ``controls`` maps names to (F,) arrays or HDF5 datasets; one feature is read at a time.
    """

    store.ensure_group(h5, schema.MASKS_GROUP)
    for feature in controls:
        for name, res in control.percentile_masks({feature: controls[feature][()]}).items():
            save_mask_bits(h5, name, res)


def save_mask_bits(h5, name: str, res, definition: str | None = None) -> None:
    """Store a compiled mask ``res`` (:class:`gesturedb.control.MaskResult`) as ``masks/<name>``
    with its definition (default: ``res.expr``) and thresholds (replacing a mask of that name)."""
    path = f"{schema.MASKS_GROUP}/{name}"
    store.delete(h5, path)
    store.create(h5, path, res.words, attrs={
        "definition": res.expr if definition is None else definition,
        "thresholds": json.dumps({k: float(v) for k, v in res.thresholds.items()}, sort_keys=True)})


def build(
    inputs: Sequence[str | os.PathLike] | str | os.PathLike,
    out_path: str | os.PathLike,
    *,
    workers: int = 1,
    recursive: bool = False,
    progress: bool | Callable = False,
    scheduler=None,
    **config,
):
    """Build a gesture database from recordings and open it.

    Parameters
    ----------
    inputs : path or list of paths / RecordingSource
        Files and/or folders; motion, audio and transcript are paired by file stem.
        :class:`RecordingSource` items are taken as they are (e.g. with a ``span_s``).
    out_path : path
        The HDF5 file to write. Written to a temporary file beside it and renamed
        on success; an existing file is replaced only then.
    workers : int
        Processes used for the per-recording work.
    progress : bool
        Show a progress bar (tqdm, on stderr).
    scheduler : str or distributed.Client, optional
        Process the recordings, and the motion graphs' edge search, as Dask tasks
        instead of local processes: ``"local:N"`` (a LocalCluster of N workers),
        ``"tcp://HOST:PORT"`` or a Client (see :mod:`gesturedb.db.cluster`). This
        process stays the only writer of the file; the database is identical to a
        local build.
    **config
        Any field of :class:`BuildConfig` (``fps``, ``chunk_frames``, ``gap_s``, ``mirror``, ...).

    Returns
    -------
    gesturedb.db.database.Database
        The new database, open for reading. ``db.pairing`` tells what was paired and skipped.
    """
    cfg = BuildConfig.from_kwargs(**config)
    if isinstance(scheduler, str):
        check_scheduler(scheduler)  # before any input is read
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    if not isinstance(workers, int) or workers < 1:
        raise ParameterError(f"workers: expected a positive integer, got {workers!r}")
    given = [x for x in inputs if isinstance(x, RecordingSource)]
    pairing = pair_inputs([x for x in inputs if not isinstance(x, RecordingSource)], recursive=recursive)
    pairing.recordings = sorted(pairing.recordings + given, key=lambda r: r.name)
    names = [r.name for r in pairing.recordings]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        first = next(r for r in pairing.recordings if r.name == twice[0])
        raise InputFileError(first.motion, f"recording name: expected each name once, got {twice[0]!r} for more than "
                                           "one recording (name them apart, e.g. with a pairing file's name column)")
    if not pairing.recordings:
        raise ParameterError(
            "inputs: expected at least one recording (a motion file .bvh/.npz and a .wav with the same stem), "
            f"found none in {', '.join(map(str, inputs))}" + ("\n" + pairing.summary() if pairing.skipped else "")
        )

    for r in pairing.recordings:
        schema.check_name(f"recording name of {r.motion}", r.name, schema.RECORDING_NAME_PATTERN)
    check_outputs({"output": out_path}, [p for r in pairing.recordings for p in (r.motion, r.audio, r.transcript)])
    words = None
    if cfg.gap_s == "auto":
        gap, words = _auto_gap(pairing.recordings)
        cfg = dataclasses.replace(cfg, gap_s=gap)
    recs: list[RecordingData] = []

    def fill(h5):
        nonlocal cfg  # its pose stride, when chosen from the data
        # each recording's per-frame arrays go into the file as it arrives and are dropped;
        # the rest (clips, chunks, words) is written once all are in
        frames = FrameWriter(h5)
        for r in _iter_processed(pairing.recordings, cfg, workers=workers, progress=progress, scheduler=scheduler,
                                 words=words):
            if recs and not _same_skeleton(recs[0].skeleton, r.skeleton):
                raise InputFileError(
                    r.source.motion,
                    f"skeleton: expected the skeleton of {recs[0].source.motion} ({len(recs[0].skeleton.names)} "
                    f"joints), got a different one ({len(r.skeleton.names)} joints); build one database per skeleton",
                )
            frames.add(r)
            recs.append(r)
            check_writes(h5)  # a full disk stops the build here, not after every recording
        timescale = fpose.motion_timescale(frames.velocity_lags, cfg.fps)
        if cfg.pose_stride is None:
            # the stride in the speaker's own time: known only now that every recording is in
            cfg = dataclasses.replace(cfg, pose_stride=fpose.timescale_pose_stride(timescale, cfg.fps))
            frames.add_pose(_pose_of(recs[0], cfg), progress=bool(progress))
        if timescale is not None:
            store.set_attrs(h5, "", {"motion_timescale_s": timescale})
        _write(h5, recs, cfg, progress, frames, scheduler)

    # one cluster for the recordings and the motion graphs ("local:N" starts it here)
    with optional_client(scheduler) as scheduler:
        # compact: the per-frame arrays, grown chunk by chunk, are stored contiguous in the database,
        # so that opening it maps them instead of reading them (gesturedb.db.database)
        write_atomically(out_path, fill, compact=True)
    pairing.notes = report_notes(recs)

    db = Database(out_path)
    db.pairing = pairing
    return db


def _pose_of(rec: RecordingData, cfg: BuildConfig):
    """The pose features of a recording's positions with ``cfg`` and ``rec``'s skeleton (that of
    every recording of a build): a function of ``(n, J, 3)`` positions, for FrameWriter.add_pose."""
    names = list(rec.skeleton.names)
    joints = {role: names.index(name) for role, name in rec.feature_joints.items()}
    stance = ankle_joints(names)
    return lambda positions: fpose.pose_features(positions, joints=joints, fps=cfg.fps, window=cfg.pose_window,
                                                 stride=cfg.pose_stride, stance=stance)


def report_notes(recs: list[RecordingData]) -> list[str]:
    """The build report's lines from every recording's notes; the same text for many files is one line."""
    by_text: dict[tuple[str, str], list[str]] = {}
    for r in recs:
        for topic, name, text in r.notes:
            by_text.setdefault((topic, text), []).append(name)
    out = []
    for (topic, text), files in by_text.items():
        who = files[0] if len(files) == 1 else f"{len(files)} files ({files[0]}, ...)"
        out.append(f"{topic}: {who}: {text}")
    return out


def _auto_gap(sources: list[RecordingSource]) -> tuple[float, list]:
    """gap_s from the pauses of every transcript (mirrored copies have the same words: not counted twice),
    and each source's transcript as read (None without one), for :func:`process_recording`."""

    pauses, total, n, words = [], 0.0, 0, []
    for src in sources:
        dur = audio_duration(src.audio)
        if src.span_s is not None:
            dur = min(dur, src.span_s[1]) - src.span_s[0]
        total += dur
        n += 1
        words.append(read_transcript(src.transcript) if src.transcript else None)
        if src.transcript:
            ws, we = np.asarray(words[-1].start_s), np.asarray(words[-1].end_s)
            if src.span_s is not None:
                keep = (ws >= src.span_s[0]) & (we <= src.span_s[1])
                ws, we = ws[keep], we[keep]
            o = np.argsort(ws, kind="stable")
            ws, we = ws[o], we[o]
            if ws.size > 1:
                pauses.append(ws[1:] - np.maximum.accumulate(we)[:-1])
    return suggest_gap_s(np.concatenate(pauses) if pauses else np.zeros(0), total, n_sequences=n), words


def _iter_processed(sources: list[RecordingSource], cfg: BuildConfig, *, workers: int, progress,
                    scheduler=None, words=None) -> Iterator[RecordingData]:
    """process_recording of every source, each result yielded in input order as soon as it and those
    before it are done (so the caller can write it and let it go); ``words``: the transcripts as
    read already (or None: each is read by its task)."""
    tasks = [(s, cfg, w) for s, w in zip(sources, words or [None] * len(sources))]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(sources), unit="rec", desc="building", disable=None)

    def done(i):
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(sources[i].name)

    try:
        if scheduler is not None:
            # tasks finish in any order; input order keeps the content independent of scheduling
            ready, nxt = {}, 0
            remote = [(_on_worker_paths(s), cfg, w) for s, cfg, w in tasks]
            for i, res in iter_on_cluster(_process_on_worker, remote, scheduler, what="the build's recordings"):
                done(i)
                for r in res:
                    r.source = sources[i]  # the paths as given, as a local build stores them
                ready[i] = res
                while nxt in ready:
                    yield from ready.pop(nxt)
                    nxt += 1
        elif workers == 1 or len(sources) == 1:
            for i, task in enumerate(tasks):
                res = process_recording(*task)
                done(i)
                yield from res
        else:
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(max_workers=min(workers, len(sources)),
                                     initializer=single_threaded_worker, initargs=(os.getpid(),)) as ex:
                # map keeps input order, so the database content does not depend on scheduling
                for i, res in enumerate(ex.map(_process_star, tasks)):
                    done(i)
                    yield from res
    finally:
        if bar is not None:
            bar.close()
