"""`gesturedb render INPUT... -o out.{mp4,gif,png}`: skeletons side by side, with speech and subtitles.

Inputs: a BVH file, an npz of joint positions (``positions (T, J, 3)``,
``parents``, ``fps`` [, ``names``]: `gesturedb.io.npz.read_joint_positions`, as
written by ``gesturedb synth --npz``), a
BEAT2/SMPL-X npz (``poses``, ``trans``), and/or a stretch of a database
(``--db DB.h5 --recording NAME --start S --end E``). Several inputs render side
by side under one camera, resampled to one frame rate.
"""
from __future__ import annotations

import os
import sys

import gesturedb
from gesturedb.errors import GestureDBError, InputFileError, ParameterError
from gesturedb.io import read_audio, read_bvh, read_smplx, read_transcript
from gesturedb.io.gltf import read_gltf
from gesturedb.io.npz import JOINT_POSITION_FIELDS, npz_keys, read_joint_positions
from gesturedb.io.outputs import check_outputs
from gesturedb.motion import resampled_length


def add_parser(sub) -> None:
    p = sub.add_parser(
        "render",
        help="render motions side by side to MP4/GIF video or a PNG contact sheet",
        description="Render BVH files, joint-position npz files (gesturedb synth --npz), SMPL-X npz files and/or a "
        "stretch of a database side by side: .mp4 (H.264, with --audio muxed in), .gif, or .png (a contact sheet).",
    )
    p.add_argument("inputs", nargs="*", metavar="INPUT", help=".bvh, .npz or .glb files")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help=".mp4, .gif or .png")
    p.add_argument("--audio", default=None, metavar="SPEECH.wav",
                   help="speech to mux into an MP4 (default for a database stretch: its recording's audio)")
    p.add_argument("--captions", default=None, help="comma-separated panel captions (default: file names)")
    p.add_argument("--transcript", default=None, metavar="WORDS", help="TextGrid/TSV/JSON shown as subtitles")
    p.add_argument("--db", default=None, metavar="DB.h5", help="add a stretch of this database as a panel")
    p.add_argument("--recording", default=None, help="recording of --db (name or index; default: the first)")
    p.add_argument("--start", type=float, default=None, metavar="S", help="start of the --db stretch, s")
    p.add_argument("--end", type=float, default=None, metavar="S", help="end of the --db stretch, s")
    p.add_argument("--fps", type=float, default=None, help="output frame rate (default: the first input's)")
    p.add_argument("--size", default=None, metavar="WxH", help="size of one panel in pixels (default: 480x540, "
                   "320x360 for a contact sheet)")
    p.add_argument("--frames", type=int, default=8, help="frames per row of a .png contact sheet (default: 8)")
    p.add_argument("--seconds", type=float, default=None, metavar="S", help="render only the first S seconds")
    p.set_defaults(run=run)


# ---------------------------------------------------------------------- inputs
def load_positions(path):
    """Joint positions of a motion file.

    Returns
    -------
    positions : ndarray [shape=(T, J, 3)], metres
    parents : ndarray [shape=(J,)], int64
    fps : float
    names : list of str or None
    """
    import numpy as np

    ext = os.path.splitext(os.fspath(path))[1].lower()
    if not os.path.isfile(path):
        raise InputFileError(path, "no such file")
    if ext == ".bvh":
        m = read_bvh(path)
        return m.positions, np.asarray(m.skeleton.parents), float(m.fps), list(m.skeleton.names)
    if ext in (".glb", ".gltf"):
        m = read_gltf(path)
        return m.positions, np.asarray(m.skeleton.parents), float(m.fps), list(m.skeleton.names)
    if ext == ".npz":
        try:
            keys = set(npz_keys(path))
            if JOINT_POSITION_FIELDS[0] in keys:
                return tuple(read_joint_positions(path))
            smplx = "poses" in keys and "trans" in keys
        except InputFileError:
            raise
        except Exception as exc:  # a damaged array (a string as fps, a ragged names list...)
            raise InputFileError(path, f"not a readable npz file ({exc})") from None
        if smplx:
            m = read_smplx(path)
            return m.positions, np.asarray(m.skeleton.parents), float(m.fps), list(m.skeleton.names)
        raise InputFileError(path, f"npz: expected joint positions (positions, parents, fps) or SMPL-X "
                                   f"(poses, trans); got fields {sorted(keys)}")
    raise InputFileError(path, f"unknown motion extension {ext or '(none)'!r}; expected .bvh, .npz or .glb")


def resample_positions(pos, fps_from: float, fps_to: float):
    """Linear interpolation of joint positions to another frame rate (display only)."""
    import numpy as np

    if fps_from == fps_to:
        return pos
    n = resampled_length(pos.shape[0], fps_from, fps_to)
    t = np.arange(n) * (fps_from / fps_to)
    i0 = np.minimum(np.floor(t).astype(np.int64), pos.shape[0] - 1)
    i1 = np.minimum(i0 + 1, pos.shape[0] - 1)
    w = (t - i0)[:, None, None]
    return (1 - w) * pos[i0] + w * pos[i1]


def facing_of(positions, names):
    """Mean facing direction of a motion from its hips and shoulders; +z when they cannot be found."""
    import numpy as np

    if names is None:
        return (0.0, 0.0, 1.0)
    try:
        from gesturedb.features.body import body_frame
        from gesturedb.io.joints import BODY_ROLES, find_joints

        idx = find_joints(names, BODY_ROLES)
        _, rot = body_frame(positions, joints=idx)
    except GestureDBError:
        return (0.0, 0.0, 1.0)
    f = rot[:, :, 2].mean(axis=0)
    f[1] = 0.0
    n = np.linalg.norm(f)
    return tuple(float(v) for v in f / n) if n > 1e-6 else (0.0, 0.0, 1.0)


def _size(text, default):
    if text is None:
        return default
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ParameterError(f"--size: expected WIDTHxHEIGHT in pixels, e.g. 480x540; got {text!r}") from None
    return w, h


def run(args) -> int:
    import numpy as np

    from gesturedb.render import fit_camera, render_contact_sheet, render_video

    ext = os.path.splitext(args.output)[1].lower()
    if ext not in (".mp4", ".gif", ".png"):
        raise ParameterError(f"-o {args.output}: expected a .mp4, .gif or .png file name")

    check_outputs({"-o": args.output}, [*args.inputs, args.audio, args.transcript, args.db])
    if not args.inputs and not args.db:
        raise ParameterError("render: expected at least one INPUT file or --db with a stretch to show")
    if args.db is None and (args.recording is not None or args.start is not None or args.end is not None):
        raise ParameterError("--recording/--start/--end: they choose a stretch of --db, which is missing")

    panels = []  # (positions, parents, fps, names, caption)
    for path in args.inputs:
        pos, par, fps, names = load_positions(path)
        panels.append([pos, par, fps, names, os.path.basename(path)])
    audio = args.audio
    if args.db:
        with gesturedb.open(args.db) as db:
            rec = db.recording(args.recording if args.recording is not None else 0)
            a, b = db.frame_range(rec.name, args.start, args.end)
            pos = np.asarray(db.joint_positions[a:b], dtype=np.float64)
            t0, t1 = (a - rec.start_frame) / db.fps, (b - rec.start_frame) / db.fps
            panels.append([pos, np.asarray(db.skeleton.parents), db.fps, list(db.joint_names),
                           f"{rec.name} {t0:g}-{t1:g} s"])
            if audio is None and not args.inputs and rec.audio_path and os.path.isfile(rec.audio_path):
                y, sr = read_audio(rec.audio_path, sr=None)
                # A recording built from part of a file (a held-out split) does not start at the
                # file's 0 s and the database does not store where it did: no sound rather than wrong sound.
                if abs(y.shape[0] / sr - rec.duration_s) <= 1.0:
                    audio = (y[int(round(t0 * sr)): int(round(t1 * sr))], sr)
                else:
                    print(f"note: {rec.name} is {rec.duration_s:.1f} s of a {y.shape[0] / sr:.1f} s audio file; "
                          "rendering without sound (pass --audio)", file=sys.stderr)
    if args.captions is not None:
        caps = [c.strip() for c in args.captions.split(",")]
        if len(caps) != len(panels):
            raise ParameterError(f"--captions: expected {len(panels)} comma-separated captions (one per panel), "
                                 f"got {len(caps)}")
        for p, c in zip(panels, caps):
            p[4] = c
    fps = float(args.fps or panels[0][2])
    if not (fps > 0):
        raise ParameterError(f"--fps: expected a positive frame rate, got {args.fps}")
    for p in panels:
        p[0] = resample_positions(p[0], p[2], fps)
        if args.seconds is not None:
            p[0] = p[0][: max(1, int(round(args.seconds * fps)))]
    out_panels = [(p[0], p[1], p[4]) for p in panels]
    size = _size(args.size, (320, 360) if ext == ".png" else (480, 540))
    camera = fit_camera([p[0] for p in panels], size=size, facing=facing_of(panels[0][0], panels[0][3]))
    captions = None
    if args.transcript:
        captions = read_transcript(args.transcript)
    if ext == ".png":
        render_contact_sheet(args.output, out_panels, n=args.frames, fps=fps, size=size, camera=camera)
    else:
        render_video(args.output, out_panels, fps=fps, audio=audio if ext == ".mp4" else None, captions=captions,
                     size=size, camera=camera)
    n = max(p[0].shape[0] for p in out_panels)
    print(f"rendered {len(out_panels)} panel(s), {n} frames ({n / fps:.2f} s at {fps:g} fps) to {args.output}")
    return 0
