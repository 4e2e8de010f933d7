"""Target rigs the retargeting tests build: other names, bone lengths, rest poses and channel layouts.

Each builder returns BVH text (the way a user hands a rig over) from a small table of
joints: (name, parent name, offset in the rig's own units).
"""
from __future__ import annotations

import numpy as np


def _rz(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _arm(prefix, side, sign, *, down_deg, arm_scale, fingers, names):
    """Joints of one arm from the clavicle out, the arm lowered by ``down_deg`` from the T-pose."""
    n = names
    # a left arm points along +x; lowering it turns about +z by -down_deg (right: mirrored)
    turn = _rz(-sign * down_deg)

    def along(v):
        v = np.array([sign * v[0], v[1], v[2]], float) * arm_scale
        return turn @ v

    sh, arm, fore, hand = (n["collar"], n["upperarm"], n["forearm"], n["hand"])
    out = [
        (f"{prefix}{sh.format(s=side)}", n["chest"], np.array([sign * 4.0, 12.0, -1.0])),
        (f"{prefix}{arm.format(s=side)}", f"{prefix}{sh.format(s=side)}", np.array([sign * 13.0, 0.0, 0.0])),
        (f"{prefix}{fore.format(s=side)}", f"{prefix}{arm.format(s=side)}", along([27.0, 0.0, 0.0])),
        (f"{prefix}{hand.format(s=side)}", f"{prefix}{fore.format(s=side)}", along([25.0, 0.0, 0.0])),
    ]
    if fingers:
        hand_name = f"{prefix}{hand.format(s=side)}"
        for finger, base in (("Index", [9.0, 0.0, 2.5]), ("Middle", [9.5, 0.0, 0.5]), ("Ring", [9.0, 0.0, -1.5]),
                             ("Pinky", [8.0, 0.0, -3.4]), ("Thumb", [2.5, -1.5, 3.0])):
            parent = hand_name
            for k, seg in enumerate((base, [3.5, 0.0, 0.0], [2.3, 0.0, 0.0])):
                name = f"{prefix}{n['finger'].format(s=side, f=finger, k=k + 1)}"
                out.append((name, parent, along(seg)))
                parent = name
    return out


def mixamo_rig(*, down_deg=40.0, arm_scale=1.1, leg_scale=0.92, fingers=True):
    """A Mixamo-named rig (``mixamorig:LeftArm``) in centimetres, A-pose (arms lowered ``down_deg``)."""
    p = "mixamorig:"
    names = {"collar": "{s}Shoulder", "upperarm": "{s}Arm", "forearm": "{s}ForeArm", "hand": "{s}Hand",
             "finger": "{s}Hand{f}{k}", "chest": p + "Spine2"}
    j = [
        (p + "Hips", None, np.array([0.0, 98.0, 0.0])),
        (p + "Spine", p + "Hips", np.array([0.0, 10.0, -1.0])),
        (p + "Spine1", p + "Spine", np.array([0.0, 12.0, 0.0])),
        (p + "Spine2", p + "Spine1", np.array([0.0, 13.0, 1.0])),
        (p + "Neck", p + "Spine2", np.array([0.0, 16.0, -1.0])),
        (p + "Head", p + "Neck", np.array([0.0, 9.0, 3.0])),
        (p + "HeadTop_End", p + "Head", np.array([0.0, 19.0, 0.0])),
    ]
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        j += _arm(p, side, sign, down_deg=down_deg, arm_scale=arm_scale, fingers=fingers, names=names)
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        j += [
            (f"{p}{side}UpLeg", p + "Hips", np.array([sign * 9.0, -6.0, 0.0])),
            (f"{p}{side}Leg", f"{p}{side}UpLeg", np.array([0.0, -44.0, 0.0]) * leg_scale),
            (f"{p}{side}Foot", f"{p}{side}Leg", np.array([0.0, -42.0, -1.0]) * leg_scale),
            (f"{p}{side}ToeBase", f"{p}{side}Foot", np.array([0.0, -6.0, 13.0])),
        ]
    return _bvh(j, channels=lambda name, root: (6 if root else 3))


def twh_rig():
    """A GENEA / Talking With Hands style rig (``b_l_arm``, twist joints) with 6 channels on every joint, cm, T-pose."""
    names = {"collar": "b_{s}_shoulder", "upperarm": "b_{s}_arm", "forearm": "b_{s}_forearm", "hand": "b_{s}_wrist",
             "finger": "b_{s}_{f}{k}", "chest": "b_spine3"}
    j = [
        ("b_root", None, np.array([0.0, 95.0, 0.0])),
        ("b_spine0", "b_root", np.array([0.0, 8.0, 0.0])),
        ("b_spine1", "b_spine0", np.array([0.0, 9.0, 0.0])),
        ("b_spine2", "b_spine1", np.array([0.0, 9.0, 0.0])),
        ("b_spine3", "b_spine2", np.array([0.0, 10.0, 0.0])),
        ("b_neck0", "b_spine3", np.array([0.0, 15.0, 0.0])),
        ("b_head", "b_neck0", np.array([0.0, 10.0, 2.0])),
    ]
    for side, sign in (("l", 1.0), ("r", -1.0)):
        arm = _arm("", side, sign, down_deg=0.0, arm_scale=0.95, fingers=True, names=names)
        # TWH names are lower case; twist helpers sit halfway along the upper arm and the forearm
        for n, par, o in ((n.lower(), par.lower(), o) for n, par, o in arm):
            if n == f"b_{side}_forearm":
                j += [(f"b_{side}_arm_twist", par, o / 2), (n, f"b_{side}_arm_twist", o / 2)]
            elif n == f"b_{side}_wrist":
                j += [(f"b_{side}_wrist_twist", par, o / 2), (n, f"b_{side}_wrist_twist", o / 2)]
            else:
                j.append((n, par, o))
    for side, sign in (("l", 1.0), ("r", -1.0)):
        j += [
            (f"b_{side}_upleg", "b_root", np.array([sign * 10.0, -4.0, 0.0])),
            (f"b_{side}_leg", f"b_{side}_upleg", np.array([0.0, -43.0, 0.0])),
            (f"b_{side}_foot_twist", f"b_{side}_leg", np.array([0.0, -20.0, 0.0])),
            (f"b_{side}_foot", f"b_{side}_foot_twist", np.array([0.0, -21.0, 0.0])),
        ]
    return _bvh(j, channels=lambda name, root: 6)


def _lower_fingers(name):
    for f in ("Index", "Middle", "Ring", "Pinky", "Thumb"):
        name = name.replace(f, f.lower())
    return name


def unreal_rig():
    """An Unreal-mannequin-named rig (``upperarm_l``, ``index_01_l``) whose root sits on the floor below the pelvis."""
    names = {"collar": "clavicle_{s}", "upperarm": "upperarm_{s}", "forearm": "lowerarm_{s}", "hand": "hand_{s}",
             "finger": "{f}_0{k}_{s}", "chest": "spine_03"}
    j = [
        ("root", None, np.array([0.0, 0.0, 0.0])),
        ("pelvis", "root", np.array([0.0, 101.0, 0.0])),
        ("spine_01", "pelvis", np.array([0.0, 11.0, 0.0])),
        ("spine_02", "spine_01", np.array([0.0, 13.0, 0.0])),
        ("spine_03", "spine_02", np.array([0.0, 14.0, 0.0])),
        ("neck_01", "spine_03", np.array([0.0, 16.0, 0.0])),
        ("head", "neck_01", np.array([0.0, 10.0, 2.0])),
    ]
    for side, sign in (("l", 1.0), ("r", -1.0)):
        j += [(_lower_fingers(n), _lower_fingers(par), o)
              for n, par, o in _arm("", side, sign, down_deg=50.0, arm_scale=1.05, fingers=True, names=names)]
    for side, sign in (("l", 1.0), ("r", -1.0)):
        j += [
            (f"thigh_{side}", "pelvis", np.array([sign * 9.5, -5.0, 0.0])),
            (f"calf_{side}", f"thigh_{side}", np.array([0.0, -46.0, 0.0])),
            (f"foot_{side}", f"calf_{side}", np.array([0.0, -43.0, 0.0])),
            (f"ball_{side}", f"foot_{side}", np.array([0.0, -7.0, 13.0])),
        ]
    return _bvh(j, channels=lambda name, root: (6 if root else 3))


def no_arms_rig():
    """Hips, spine, head and legs only: nothing to carry gestures."""
    j = [("Hips", None, np.array([0.0, 1.0, 0.0])), ("Spine", "Hips", np.array([0.0, 0.3, 0.0])),
         ("Head", "Spine", np.array([0.0, 0.4, 0.0])), ("LeftUpLeg", "Hips", np.array([0.1, -0.05, 0.0])),
         ("LeftLeg", "LeftUpLeg", np.array([0.0, -0.45, 0.0])), ("RightUpLeg", "Hips", np.array([-0.1, -0.05, 0.0])),
         ("RightLeg", "RightUpLeg", np.array([0.0, -0.45, 0.0]))]
    return _bvh(j, channels=lambda name, root: 6 if root else 3)


def _bvh(joints, *, channels):
    """BVH text of a joint table; one frame of rest pose (with the OFFSETs as position channels where there are 6)."""
    defined = {name for name, _, _ in joints}
    orphans = [name for name, parent, _ in joints if parent is not None and parent not in defined]
    if orphans:
        raise ValueError(f"rig table: joints whose parent is not defined: {orphans}")
    kids = {}
    for name, parent, _ in joints:
        kids.setdefault(parent, []).append(name)
    off = {name: o for name, _, o in joints}
    lines, frame = ["HIERARCHY"], []

    def emit(name, depth, root):
        ind = "  " * depth
        n_ch = channels(name, root)
        lines.append(f"{ind}{'ROOT' if root else 'JOINT'} {name}")
        lines.append(ind + "{")
        lines.append(f"{ind}  OFFSET {' '.join(f'{x:.4f}' for x in off[name])}")
        if n_ch == 6:
            lines.append(f"{ind}  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
            frame.extend(list(off[name]) + [0.0, 0.0, 0.0])
        else:
            lines.append(f"{ind}  CHANNELS 3 Zrotation Xrotation Yrotation")
            frame.extend([0.0, 0.0, 0.0])
        children = kids.get(name, [])
        if not children:
            lines.extend([f"{ind}  End Site", f"{ind}  {{", f"{ind}    OFFSET 0 3 0", f"{ind}  }}"])
        for c in children:
            emit(c, depth + 1, False)
        lines.append(ind + "}")

    emit(kids[None][0], 0, True)
    lines += ["MOTION", "Frames: 1", "Frame Time: 0.0333333", " ".join(f"{x:.4f}" for x in frame)]
    return "\n".join(lines) + "\n"
