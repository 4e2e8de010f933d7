"""BVH files in the conventions of the capture pipelines users bring, written from a real SMPL-X Motion.

Each writer renames the SMPL-X joints as the dataset does, adds its helper joints,
uses its channel layout, length unit and frame rate, and computes the Euler angles
with scipy (not with the package's own conversion), so reading the file back through
gesturedb is an independent check:

- GENEA / Talking With Hands: ``body_world`` root carrying the translation, ``b_root``
  (the pelvis) below it, ``b_l_wrist``-style names, 6 channels on **every** joint,
  centimetres, 30 fps.
- ZEGGS: ``LeftHand``/``LeftHandIndex1`` names, ``Z Y X`` rotation channels, ``*End``
  helper joints (``HeadEnd``, ``LeftHandIndexEnd``) that never rotate, centimetres, 60 fps.
- Mixamo: ``mixamorig:`` prefixes, 6-channel root, ``Z X Y`` elsewhere, centimetres, 120 fps.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

_FINGERS = ("index", "middle", "pinky", "ring", "thumb")


def _bvh_style(name: str, prefix: str = "") -> str:
    """SMPL-X joint name -> ZEGGS / Mixamo style."""
    fixed = {"pelvis": "Hips", "spine1": "Spine", "spine2": "Spine1", "spine3": "Spine2", "neck": "Neck",
             "head": "Head", "jaw": "Jaw"}
    if name in fixed:
        return prefix + fixed[name]
    side, part = name.split("_", 1)
    side = side.capitalize()
    parts = {"hip": "UpLeg", "knee": "Leg", "ankle": "Foot", "foot": "ToeBase", "collar": "Shoulder",
             "shoulder": "Arm", "elbow": "ForeArm", "wrist": "Hand", "eye": "Eye"}
    if part in parts:
        return f"{prefix}{side}{parts[part]}"
    finger, k = part[:-1], part[-1]
    assert finger in _FINGERS, name
    return f"{prefix}{side}Hand{finger.capitalize()}{k}"


def _genea_style(name: str) -> str:
    """SMPL-X joint name -> GENEA / Talking With Hands style (``b_l_wrist``)."""
    fixed = {"pelvis": "b_root", "spine1": "b_spine0", "spine2": "b_spine1", "spine3": "b_spine2",
             "neck": "b_neck0", "head": "b_head", "jaw": "b_jaw"}
    if name in fixed:
        return fixed[name]
    side, part = name.split("_", 1)
    s = side[0]
    parts = {"hip": "upleg", "knee": "leg", "ankle": "foot", "foot": "toe", "collar": "shoulder",
             "shoulder": "arm", "elbow": "forearm", "wrist": "wrist", "eye": "eye"}
    if part in parts:
        return f"b_{s}_{parts[part]}"
    return f"b_{s}_{part}"


CONVENTIONS = {
    # name map, channels(joint kind) -> (position?, rotation order), unit (m per unit), fps, helpers, world root
    "genea": dict(rename=_genea_style, rot_order="ZXY", all_positions=True, unit=0.01, fps=30.0, end_helpers=False,
                  world_root="body_world"),
    "zeggs": dict(rename=_bvh_style, rot_order="ZYX", all_positions=False, unit=0.01, fps=60.0, end_helpers=True,
                  world_root=None),
    "mixamo": dict(rename=lambda n: _bvh_style(n, "mixamorig:"), rot_order="ZXY", all_positions=False, unit=0.01,
                   fps=120.0, end_helpers=False, world_root=None),
}


def write_convention(path, motion, convention: str) -> dict[str, str]:
    """Write ``motion`` (an SMPL-X Motion) as a BVH file of one pipeline's conventions.

    Returns
    -------
    dict
        SMPL-X joint name -> joint name in the file.
    """
    c = CONVENTIONS[convention]
    if motion.fps != c["fps"]:
        motion = motion.resample(c["fps"])
    sk = motion.skeleton
    names = {n: c["rename"](n) for n in sk.names}
    unit = c["unit"]
    order = c["rot_order"]
    kids: dict[int, list[int]] = {}
    for j in range(1, sk.n_joints):
        kids.setdefault(int(sk.parents[j]), []).append(j)
    F = motion.n_frames
    quat_xyzw = np.roll(motion.rotations, -1, axis=-1)  # w, x, y, z -> x, y, z, w for scipy
    lines, cols = ["HIERARCHY"], []
    pos_ch = "Xposition Yposition Zposition"
    rot_ch = " ".join(f"{a}rotation" for a in order)

    def angles(j):
        return Rotation.from_quat(quat_xyzw[:, j]).as_euler(order, degrees=True)  # intrinsic: R = R1 R2 R3

    def emit(j, depth):
        ind = "\t" * depth
        is_root = j == 0 and c["world_root"] is None
        off = sk.offsets[j] / unit
        if j == 0 and c["world_root"] is not None:
            off = np.zeros(3)  # body_world carries the translation; b_root sits on it
        lines.append(f"{ind}{'ROOT' if is_root else 'JOINT'} {names[sk.names[j]]}")
        lines.append(ind + "{")
        lines.append(f"{ind}\tOFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
        if is_root or c["all_positions"]:
            lines.append(f"{ind}\tCHANNELS 6 {pos_ch} {rot_ch}")
            cols.append(motion.root_positions / unit if is_root else np.repeat(off[None], F, axis=0))
        else:
            lines.append(f"{ind}\tCHANNELS 3 {rot_ch}")
        cols.append(angles(j))
        children = kids.get(j, [])
        for k in children:
            emit(k, depth + 1)
        end = sk.end_sites.get(j)
        if c["end_helpers"] and not children:
            # ZEGGS: a helper joint at the tip of every chain, which never rotates
            tip = (end if end is not None else sk.offsets[j] * 0.3) / unit
            helper = names[sk.names[j]].rstrip("0123456789") + "End"
            lines.extend([f"{ind}\tJOINT {helper}", f"{ind}\t{{", f"{ind}\t\tOFFSET {tip[0]:.6f} {tip[1]:.6f} {tip[2]:.6f}",
                          f"{ind}\t\tCHANNELS 3 {rot_ch}", f"{ind}\t\tEnd Site", f"{ind}\t\t{{",
                          f"{ind}\t\t\tOFFSET 0.000000 1.000000 0.000000", f"{ind}\t\t}}", f"{ind}\t}}"])
            cols.append(np.zeros((F, 3)))
        elif not children:
            tip = (end if end is not None else np.array([0.0, 0.02, 0.0])) / unit
            lines.extend([f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {tip[0]:.6f} {tip[1]:.6f} {tip[2]:.6f}",
                          f"{ind}\t}}"])
        lines.append(ind + "}")

    if c["world_root"] is not None:
        lines += [f"ROOT {c['world_root']}", "{", "\tOFFSET 0.000000 0.000000 0.000000",
                  f"\tCHANNELS 6 {pos_ch} {rot_ch}"]
        cols.append(motion.root_positions / unit)
        cols.append(np.zeros((F, 3)))
        emit(0, 1)
        lines.append("}")
    else:
        emit(0, 0)
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {1.0 / motion.fps:.6f}"]
    data = np.concatenate(cols, axis=1)
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
        np.savetxt(f, data, fmt="%.6f")
    return names
