"""`gesturedb retarget IN.bvh --to RIG.bvh -o OUT.bvh|OUT.glb` and the --target-skeleton option of synth/export."""
from __future__ import annotations

import sys

from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io import check_motion_output, read_motion, write_motion
from gesturedb.io.outputs import check_outputs


def add_target_options(p, *, required: bool = False) -> None:
    """The rig options shared by `retarget`, `synth` and `export`."""
    flag = ("--to",) if required else ("--target-skeleton",)
    p.add_argument(*flag, dest="target_skeleton", required=required, default=None, metavar="RIG.bvh|RIG.glb",
                   help="retarget onto this rig: a BVH (hierarchy and rest pose; its motion is ignored) or a "
                        "glTF skin")
    p.add_argument("--map", action="append", default=[], metavar="TARGET=SOURCE",
                   help="pair a target joint with a source joint by name, overriding the name matching "
                        "(repeatable; TARGET= leaves it at rest)")


def parse_map(items) -> dict:
    mapping = {}
    for item in items:
        t, sep, s = item.partition("=")
        if not sep or not t:
            raise ParameterError(f"--map: expected TARGET=SOURCE joint names; got {item!r}")
        mapping[t.strip()] = s.strip()
    return mapping


def load_target(args):
    """Read ``args.target_skeleton`` once (None if unset): commands call it before their long work, so a
    broken rig fails at once rather than after a synthesis."""
    if not getattr(args, "target_skeleton", None):
        return None
    if getattr(args, "_target_rig", None) is None:
        from gesturedb.retarget import load_rig

        args._target_rig = load_rig(args.target_skeleton)
    return args._target_rig


def apply_target(args, motion):
    """Retarget ``motion`` if ``args.target_skeleton`` is set; the report goes to stderr."""
    if not args.target_skeleton:
        return motion
    from gesturedb.retarget import retarget

    res = retarget(motion, load_target(args), mapping=parse_map(args.map))
    print(res.report(), file=sys.stderr)
    return res.motion


def speech_beside(output, audio):
    """For a .glb output, the speech as a 16-bit WAV of the same stem (glTF has no audio); its path or None."""
    import os

    if not audio or os.path.splitext(output)[1].lower() != ".glb":
        return None
    import soundfile as sf

    wav = os.path.splitext(output)[0] + ".wav"
    if os.path.abspath(wav) == os.path.abspath(audio):
        return None
    try:
        data, sr = sf.read(audio, always_2d=False)
        sf.write(wav, data, sr, subtype="PCM_16")
    except (RuntimeError, OSError) as exc:  # soundfile's errors for unreadable/unwritable files
        raise InputFileError(wav, f"cannot write the speech beside the .glb: {exc}") from None
    return wav


def add_parser(sub) -> None:
    p = sub.add_parser("retarget", help="move motion onto another rig (BVH or glTF skin); write BVH or glTF",
                       description="Pairs joints by body part across naming schemes (SMPL-X, GENEA/TWH, ZEGGS, "
                                   "Mixamo, Unreal), transfers global rotations relative to each rig's rest pose "
                                   "and scales the hips trajectory by the hip-height ratio.")
    p.add_argument("input", metavar="IN.bvh|IN.npz|IN.glb")
    add_target_options(p, required=True)
    p.add_argument("-o", "--output", required=True, metavar="OUT.bvh|OUT.glb")
    p.set_defaults(run=run)


def run(args) -> int:
    check_motion_output(args.output)
    check_outputs({"-o": args.output}, [args.input, args.target_skeleton])
    motion = read_motion(args.input)
    out = apply_target(args, motion)
    write_motion(args.output, out)
    print(f"wrote {args.output}: {out.n_frames} frames at {out.fps:g} fps on {out.skeleton.n_joints} joints")
    return 0
