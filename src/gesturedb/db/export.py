"""A keyword sub-database exported as a complete database file of its own.

The export holds only the occurrences' frames (re-chunked, clips and signatures
recomputed), so it opens, searches and synthesizes like any database.
"""
from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass

import numpy as np

from gesturedb import control
from gesturedb._version import __version__
from gesturedb.db import schema, store
from gesturedb.db.build import write_default_masks
from gesturedb.db.database import Database
from gesturedb.db.keywords import SubDatabase, _check_int, _open, _tables, _write_subdb, get_subdatabase, time_to_frames
from gesturedb.db.storage import write_atomically
from gesturedb.errors import ParameterError, SchemaError
from gesturedb.features import rhythm as frhythm
from gesturedb.features import segments as fseg
from gesturedb.features import style as fstyle


def export_keyword(db_path, word: str, out_path, *, chunk_frames: int | None = None):
    """Write a sub-database as a complete gesture database file of its own.

    Every occurrence stretch becomes a recording named ``<recording>@<start_s>``
    (the stretch start within the source recording, 3 decimals; a repeated name
    gets ``#2``, ``#3``...). The new file follows :mod:`gesturedb.db.schema`:

    * per-frame arrays, controls and the recording columns are copied from the
      source frames (pose features keep their source history, so the frames are
      the same numbers as in the source);
    * the skeleton, audio mean/std, ``config``, ``feature_joints`` and the motion timescale are copied;
    * words: those whose start lies in a stretch, times made relative to it and
      their end clipped to it;
    * chunks: one per stretch (``chunk_frames=None``) or fixed chunks of
      ``chunk_frames`` within each stretch;
    * word-gap clips are recomputed on each stretch's words with the source's
      ``gap_s``; their rhythm and style signatures are measured on the whole
      source recording (so a speed minimum right at a stretch edge is still
      seen, as in a build);
    * the default percentile masks are recomputed over the new frames
      (:func:`gesturedb.db.build.write_default_masks`); other saved masks of the
      source keep their bits on the copied frames;
    * the sub-database itself, every stretch whole, so the keyword works in
      synthesis with the exported file.

    Parameters
    ----------
    db_path : path
        The source database (not modified).
    word : str
        A keyword with a sub-database in it.
    out_path : path
        The new file, written to a temporary file beside it and renamed.
    chunk_frames : int or None
        See above.

    Returns
    -------
    gesturedb.db.database.Database
        The new database, open for reading.
    """

    if chunk_frames is not None:
        chunk_frames = _check_int("chunk_frames", chunk_frames, 1)
    out_path = os.fspath(out_path)
    if os.path.exists(out_path) and os.path.samefile(out_path, db_path):
        raise ParameterError(f"output: {out_path} is the source database; export to another file")
    with _open(db_path) as db:
        sub = get_subdatabase(db, word)
        plan = _export_plan(db, sub, chunk_frames)
        write_atomically(out_path, lambda h5: _write_export(h5, db, sub, plan))
    return Database(out_path)


@dataclass
class _ExportPlan:
    frames: np.ndarray      # (F',) source frame of every new frame
    names: list
    starts: np.ndarray      # (R',) new start frames
    lengths: np.ndarray     # (R',)
    src_rec: np.ndarray     # (R',) source recording index
    src_first: np.ndarray   # (R',) stretch start within the source recording, frames
    words: list             # per stretch: (source word indices, start_s, end_s, text)
    keyword_word: np.ndarray  # (R',) index of the occurrence in the new words table
    chunks: tuple           # (start, length, recording) new
    clips: dict


def _export_plan(db, sub: SubDatabase, chunk_frames: int | None) -> _ExportPlan:
    fps = db.fps
    recs = db.recordings
    t = _tables(db)
    n = len(sub)
    lengths = sub.length.astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    frames = np.concatenate([np.arange(a, a + L, dtype=np.int64) for a, L in zip(sub.start, lengths)])
    src_rec = sub.recording.astype(np.int64)
    src_first = sub.start - t.rec_start[src_rec]

    names, seen = [], Counter()
    for r, a in zip(src_rec, src_first):
        base = f"{recs[r].name}@{a / fps:.3f}"
        seen[base] += 1
        names.append(base if seen[base] == 1 else f"{base}#{seen[base]}")

    w_first, _ = time_to_frames(t.w_start, t.w_end, fps)
    words, keyword_word, base_w = [], np.empty(n, dtype=np.int64), 0
    for i in range(n):
        r, a, L = src_rec[i], int(src_first[i]), int(lengths[i])
        sel = np.flatnonzero((t.w_rec == r) & (w_first >= a) & (w_first < a + L))
        s0 = a / fps
        ws = np.clip(t.w_start[sel] - s0, 0.0, None)
        we = np.clip(t.w_end[sel] - s0, ws, L / fps)
        hit = np.flatnonzero(sel == sub.word_index[i])
        if hit.size != 1:  # the stretch is built around the word's frames, so this is a corrupt file
            raise SchemaError(db.path, f"{schema.SUBDB_GROUP}/{sub.word}: occurrence {i} (word "
                              f"{int(sub.word_index[i])}) does not lie inside its stretch")
        keyword_word[i] = base_w + int(hit[0])
        words.append((sel, ws, we, [t.w_text[j] for j in sel]))
        base_w += sel.size

    if chunk_frames is None:
        chunks = (starts.copy(), lengths.copy(), np.arange(n, dtype=np.int32))
    else:
        parts = [fseg.fixed_chunks(int(L), length=chunk_frames) for L in lengths]
        chunks = (
            np.concatenate([s + b for (s, _), b in zip(parts, starts)]).astype(np.int64),
            np.concatenate([ln for _, ln in parts]).astype(np.int64),
            np.concatenate([np.full(len(s), i, np.int32) for i, (s, _) in enumerate(parts)]),
        )

    gap_s = float(db.config.get("gap_s", 0.4))
    names_idx = {name: j for j, name in enumerate(db.joint_names)}
    joints = {role: names_idx[name] for role, name in db.feature_joints.items() if name in names_idx}
    pos_cache: dict[int, tuple] = {}
    cl = {k: [] for k in ("start", "length", "recording", "word_start", "word_end",
                          "rhythm_audio", "rhythm_motion", "style")}
    base_w = 0
    for i in range(n):
        r, a, L = int(src_rec[i]), int(src_first[i]), int(lengths[i])
        _, ws, we, _ = words[i]
        c = fseg.word_gap_clips(ws, we, n_frames=L, fps=fps, gap_s=gap_s)
        if r not in pos_cache:
            rec = recs[r]
            pos = np.asarray(db.joint_positions[rec.start_frame:rec.stop_frame], dtype=np.float64)
            pos_cache[r] = (pos, frhythm.hand_speed(pos, joints=joints, fps=fps))
        pos, speed = pos_cache[r]
        cl["start"].append(c.start + starts[i])
        cl["length"].append(c.length)
        cl["recording"].append(np.full(len(c.start), i, np.int32))
        cl["word_start"].append(c.word_start + base_w)
        cl["word_end"].append(c.word_end + base_w)
        cl["rhythm_audio"].append(np.atleast_1d(np.asarray(
            frhythm.audio_rhythm(ws, start_s=c.start / fps, end_s=(c.start + c.length) / fps), dtype=np.uint32)))
        cl["rhythm_motion"].append(np.atleast_1d(np.asarray(
            frhythm.motion_rhythm(speed, start=c.start + a, length=c.length, fps=fps), dtype=np.uint32)))
        cl["style"].append(fstyle.style_signatures(pos, joints=joints, fps=fps, starts=c.start + a, lengths=c.length))
        base_w += len(ws)
    clips = {k: np.concatenate(v) for k, v in cl.items()}
    return _ExportPlan(frames=frames, names=names, starts=starts, lengths=lengths, src_rec=src_rec,
                       src_first=src_first, words=words, keyword_word=keyword_word, chunks=chunks, clips=clips)


def _write_export(h5, db, sub: SubDatabase, p: _ExportPlan) -> None:
    W = schema.write
    dims: dict[str, int] = {}
    recs = db.recordings
    F = int(p.frames.shape[0])
    fr = p.frames
    src = [recs[int(r)] for r in p.src_rec]

    store.set_attrs(h5, "", {"schema_version": schema.SCHEMA_VERSION, "gesturedb_version": __version__,
                             "fps": float(db.fps), "n_frames": F})
    if db.motion_timescale_s is not None:  # what the copied pose features' stride came from
        store.set_attrs(h5, "", {"motion_timescale_s": db.motion_timescale_s})
    schema.write_json_attr(h5, "config", db.config)
    schema.write_json_attr(h5, "feature_joints", db.feature_joints)

    W(h5, schema.RECORDING_NAME, p.names, dims)
    W(h5, schema.RECORDING_SPEAKER, [r.speaker for r in src], dims)
    W(h5, schema.RECORDING_MOTION_PATH, [r.motion_path for r in src], dims)
    W(h5, schema.RECORDING_AUDIO_PATH, [r.audio_path for r in src], dims)
    W(h5, schema.RECORDING_TRANSCRIPT_PATH, [r.transcript_path for r in src], dims)
    W(h5, schema.RECORDING_START_FRAME, p.starts, dims)
    W(h5, schema.RECORDING_N_FRAMES, p.lengths, dims)
    W(h5, schema.RECORDING_DURATION_S, p.lengths / db.fps, dims)
    W(h5, schema.RECORDING_SOURCE_FPS, np.array([r.source_fps for r in src], dtype=np.float64), dims)
    W(h5, schema.RECORDING_MIRRORED, np.array([r.mirrored for r in src], dtype=bool), dims)

    W(h5, schema.POSE_FEATURES, db.pose_features[fr], dims)
    W(h5, schema.AUDIO_FEATURES, db.audio_features[fr], dims)
    W(h5, schema.AUDIO_DELTAS, db.audio_deltas[fr], dims)
    W(h5, schema.JOINT_POSITIONS, db.joint_positions[fr], dims)
    W(h5, schema.LOCAL_ROTATIONS, db.local_rotations[fr], dims)
    W(h5, schema.ROOT_POSITIONS, db.root_positions[fr], dims)
    W(h5, schema.FRAME_RECORDING, np.repeat(np.arange(len(p.names), dtype=np.int32), p.lengths), dims)
    W(h5, schema.AUDIO_MEAN, db.audio_mean, dims)
    W(h5, schema.AUDIO_STD, db.audio_std, dims)

    for path in (schema.SKELETON_NAMES, schema.SKELETON_PARENTS, schema.SKELETON_OFFSETS, schema.SKELETON_CHANNEL_ORDERS,
                 schema.SKELETON_END_SITE_JOINTS, schema.SKELETON_END_SITE_OFFSETS):
        W(h5, path, db.read(path), dims)

    W(h5, schema.CHUNK_START, p.chunks[0], dims)
    W(h5, schema.CHUNK_LENGTH, p.chunks[1], dims)
    W(h5, schema.CHUNK_RECORDING, p.chunks[2], dims)

    for key in ("start", "length", "recording", "word_start", "word_end", "rhythm_audio", "rhythm_motion"):
        W(h5, f"{schema.CLIPS}/{key}", p.clips[key], dims)
    W(h5, schema.CLIP_STYLE, p.clips["style"].astype(np.float32).reshape(-1, 3), dims)

    W(h5, schema.WORD_RECORDING, np.concatenate([np.full(len(w[0]), i, np.int32) for i, w in enumerate(p.words)]), dims)
    W(h5, schema.WORD_START_S, np.concatenate([w[1] for w in p.words]), dims)
    W(h5, schema.WORD_END_S, np.concatenate([w[2] for w in p.words]), dims)
    W(h5, schema.WORD_TEXT, [x for w in p.words for x in w[3]], dims)

    controls = {k: np.ascontiguousarray(v[fr], dtype=np.float32) for k, v in db.controls.items()}
    if controls:
        store.ensure_group(h5, schema.CONTROLS_GROUP)
        for k, v in controls.items():
            src_attrs = db.control_attrs(k)
            store.create(h5, f"{schema.CONTROLS_GROUP}/{k}", v,
                         attrs={a: src_attrs[a] for a in ("unit", "doc") if a in src_attrs})
        write_default_masks(h5, controls)
    if db.has(schema.MASKS_GROUP):
        store.ensure_group(h5, schema.MASKS_GROUP)
        taken = set(store.members(h5, schema.MASKS_GROUP))
        for name in sorted(db.masks):
            if name in taken:  # a default mask, recomputed above for the new frames
                continue
            bits = control.unpack_bits(db.masks[name], db.n_frames)[fr]
            store.create(h5, f"{schema.MASKS_GROUP}/{name}", control.pack_bits(bits), attrs=db.mask_attrs(name))

    definition = dict(sub.definition)
    definition["exported_from"] = {"database": os.path.abspath(db.path), "occurrences": len(sub)}
    _write_subdb(h5, SubDatabase(
        word=sub.word, start=p.starts, length=p.lengths, recording=np.arange(len(p.names), dtype=np.int32),
        word_index=p.keyword_word, mask=control.full_mask(F), definition=definition,
    ))
