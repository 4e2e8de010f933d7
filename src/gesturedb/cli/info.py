"""`gesturedb info DB.h5`: a readable summary of a database."""
from __future__ import annotations

import json
import os

import gesturedb
from gesturedb.db import schema
from gesturedb.errors import ParameterError


def add_parser(sub) -> None:
    p = sub.add_parser("info", help="summarise a gesture database")
    p.add_argument("db", metavar="DB.h5", nargs="?", help="the database (not needed with --schema)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--schema", action="store_true", help="print the file schema instead")
    p.set_defaults(run=run)


def summary(db) -> dict:
    import numpy as np

    from gesturedb.db.keywords import subdatabases

    recs = db.recordings
    chunks, clips = db.chunks, db.clips
    return {
        "path": db.path,
        "gesturedb_version": db.gesturedb_version,
        "fps": db.fps,
        "frames": db.n_frames,
        "duration_s": round(db.n_frames / db.fps, 3),
        "recordings": [{"name": r.name, "speaker": r.speaker, "duration_s": round(r.duration_s, 3),
                        "frames": r.n_frames, "source_fps": r.source_fps, "mirrored": r.mirrored} for r in recs],
        "speakers": sorted({r.speaker for r in recs}),
        "chunks": {"count": len(chunks), "frames": int(np.median(chunks.length)) if len(chunks) else 0},
        "clips": {"count": len(clips),
                  "mean_s": round(float(np.mean(clips.length)) / db.fps, 3) if len(clips) else 0.0},
        "words": len(db.words),
        "skeleton": {"joints": len(db.joint_names), "root": db.joint_names[0]},
        "feature_joints": db.feature_joints,
        "features": {"pose": db.frame_shape("pose_features")[1], "audio": db.frame_shape("audio_features")[1],
                     "pose_stride": db.config.get("pose_stride"), "motion_timescale_s": db.motion_timescale_s},
        "controls": {k: db.control_units[k] for k in db.controls},
        "masks": db.mask_definitions,
        "keywords": {w: {"occurrences": len(sd), "seconds": round(sd.n_frames / db.fps, 3)}
                     for w, sd in subdatabases(db).items()},
        "config": db.config,
        "shards": [{"file": e["file"], "frames": list(e["frames"])} for e in db.shard_entries],
    }


def run(args) -> int:
    if args.schema:
        print(schema.describe())
        return 0
    if args.db is None:
        raise ParameterError("DB.h5: expected a database to summarise (or --schema for the file layout)")
    with gesturedb.open(args.db) as db:
        s = summary(db)
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    mins, secs = divmod(s["duration_s"], 60)
    print(f"{s['path']}  (gesturedb {s['gesturedb_version']}, schema {schema.SCHEMA_VERSION})")
    print(f"  duration     {int(mins)} min {secs:.1f} s  = {s['frames']} frames at {s['fps']:g} fps")
    print(f"  speakers     {', '.join(s['speakers'])}")
    print(f"  recordings   {len(s['recordings'])}")
    for r in s["recordings"]:
        print(f"    {r['name']:<32} {r['duration_s']:8.2f} s  {r['frames']:7d} frames  (source {r['source_fps']:g} fps"
              f"{', mirrored' if r['mirrored'] else ''})")
    if s["shards"]:
        print(f"  shards       {len(s['shards'])} file(s) beside this index: " + ", ".join(
            f"{os.path.basename(e['file'])} (frames {e['frames'][0]}..{e['frames'][1]})" for e in s["shards"]))
    print(f"  chunks       {s['chunks']['count']} x {s['chunks']['frames']} frames")
    print(f"  clips        {s['clips']['count']} word-gap clips, mean {s['clips']['mean_s']:.2f} s;  {s['words']} words")
    print(f"  skeleton     {s['skeleton']['joints']} joints, root {s['skeleton']['root']}")
    f = s["features"]
    stride = "" if f["pose_stride"] is None else f" (frames {f['pose_stride']} apart" + (
        "" if f["motion_timescale_s"] is None else f"; the motion's timescale {f['motion_timescale_s']:.3f} s") + ")"
    print(f"  features     pose {f['pose']} values/frame{stride}, audio {f['audio']} values/frame")
    print("  feature joints " + ", ".join(f"{k}={v}" for k, v in s["feature_joints"].items()))
    if s["controls"]:
        print("  controls     " + ", ".join(f"{k} [{u}]" for k, u in s["controls"].items()))
    if s["masks"]:
        print(f"  masks        {len(s['masks'])}: " + ", ".join(s["masks"]))
    kw = s["keywords"]
    if kw:
        print(f"  keywords     {len(kw)} keyword sub-database(s): " + ", ".join(
            f"{w} ({k['occurrences']} x, {k['seconds']:.1f} s)" for w, k in kw.items())
            + "; used when the transcript says them")
    else:
        print(f"  keywords     none (gesturedb keywords {s['path']} add WORD: gestures from the speaker's own WORDs "
              "whenever the speech says WORD)")
    cfg = s["config"]
    print("  config       " + ", ".join(f"{k}={cfg[k]}" for k in sorted(cfg)))
    return 0
