"""Find the joints the features need, whatever the skeleton calls them.

A role such as ``left_wrist`` is matched against joint names by splitting each
name into words (separators and camelCase: ``mixamorig:LeftHandIndex1`` ->
``left hand index 1``), reading the side (``left``/``l``, ``right``/``r``),
dropping rig prefixes (``mixamorig``, GENEA's ``b``), and comparing what is
left with a list of part names per role, best first. This covers SMPL-X
(``left_wrist``, ``left_index1``), GENEA / Talking With Hands (``b_l_wrist``,
``b_l_index1``, ``b_root``), ZEGGS and Mixamo (``LeftHand``,
``LeftHandIndex1``, ``mixamorig:LeftHand``) and generic BVH rigs
(``LeftWrist``, ``LeftForeArm``/``LeftElbow``, ``LeftArm``, ``LeftUpLeg``,
``Hips``), case- and separator-insensitively.

Shoulder means the shoulder *joint* (top of the upper arm): BVH rigs call it
``LeftArm`` and use ``LeftShoulder`` for the clavicle, SMPL-X calls it
``left_shoulder`` and the clavicle ``left_collar``; an upper-arm name is
therefore preferred and ``shoulder`` is the fallback.
"""
from __future__ import annotations

import re

from gesturedb.errors import InputFileError, ParameterError

__all__ = ["BODY_ROLES", "FEATURE_ROLES", "find_joints"]

FEATURE_ROLES = ("left_wrist", "right_wrist", "left_elbow", "right_elbow",
                 "left_index1", "right_index1", "left_pinky1", "right_pinky1")
BODY_ROLES = ("root", "left_hip", "right_hip", "left_shoulder", "right_shoulder")

# Part names per role (side removed, words joined), best first.
_PARTS = {
    "wrist": ("wrist", "hand"),
    "elbow": ("elbow", "forearm", "lowerarm"),
    "index1": ("index1", "handindex1", "indexfinger1", "fingerindex1", "index01"),
    "pinky1": ("pinky1", "handpinky1", "little1", "handlittle1", "littlefinger1", "pinkyfinger1", "fingerpinky1",
               "fingerlittle1"),
    "shoulder": ("arm", "upperarm", "uparm", "humerus", "shoulder"),
    "hip": ("upleg", "upperleg", "thigh", "femur", "hip"),
}
_ROOT_PARTS = ("hips", "pelvis", "root", "spine0")
_SIDES = {"left": "left", "l": "left", "right": "right", "r": "right"}
# words that carry no anatomy: rig namespaces and prefixes, "joint"/"jnt" suffixes
_NOISE = frozenset({"mixamorig", "b", "bip", "bip01", "bip001", "joint", "jnt", "j", "bn", "bone", "def"})
_WORDS = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+")


def _parse(name: str) -> tuple[str | None, str]:
    """(side or None, part) of a joint name, e.g. ``mixamorig:LeftHandIndex1`` -> ("left", "handindex1")."""
    base = name.rsplit(":", 1)[-1]
    words = [w.lower() for w in _WORDS.findall(base)]
    side = None
    kept = []
    for w in words:
        if side is None and w in _SIDES:
            side = _SIDES[w]
        elif w not in _NOISE:
            # "01" and "1" are the same finger segment
            kept.append(str(int(w)) if w.isdigit() else w)
    return side, "".join(kept)


def _role_spec(role: str) -> tuple[str | None, tuple[str, ...]]:
    if role == "root":
        return None, _ROOT_PARTS
    side, _, part = role.partition("_")
    return side, _PARTS[part]


def find_joints(names, roles=FEATURE_ROLES + BODY_ROLES, *, mapping=None, source=None) -> dict[str, int]:
    """Map roles to joint indices by name.

    Parameters
    ----------
    names : sequence of str [length J]
        Joint names, e.g. ``Skeleton.names`` (index 0 is the root).
    roles : sequence of str
        Roles to find, from `FEATURE_ROLES` and `BODY_ROLES`.
    mapping : dict of str to str, optional
        ``{role: joint_name}`` overrides for roles the names do not reveal
        (exact joint names).
    source : str or os.PathLike, optional
        The file the names came from; errors are then `InputFileError`.

    Returns
    -------
    dict of str to int
        Role -> joint index, for every role in ``roles``. ``root`` falls back to
        joint 0 when no joint is called hips/pelvis/root.

    Raises
    ------
    InputFileError
        (``ParameterError`` without ``source``) if a role has no joint: the
        message names the missing roles and lists the joints there are.
    ParameterError
        Unknown role, or a mapping that names a joint that does not exist.
    """
    names = [str(n) for n in names]
    known = FEATURE_ROLES + BODY_ROLES
    roles = tuple(roles)
    unknown = [r for r in roles if r not in known]
    mapping = dict(mapping or {})
    unknown += [r for r in mapping if r not in known and r not in unknown]
    if unknown:
        raise ParameterError(f"roles: unknown {', '.join(map(repr, unknown))}; known roles: {', '.join(known)}")
    for role, joint in mapping.items():
        if joint not in names:
            raise ParameterError(f"mapping[{role!r}]: no joint named {joint!r}; joints: {', '.join(names)}")

    parsed = [_parse(n) for n in names]
    found: dict[str, int] = {}
    missing = []
    for role in roles:
        if role in mapping:
            found[role] = names.index(mapping[role])
            continue
        side, parts = _role_spec(role)
        hit = None
        for part in parts:
            hit = next((j for j, (s, p) in enumerate(parsed) if s == side and p == part), None)
            if hit is not None:
                break
        if hit is None and role == "root" and names:
            hit = 0  # the root joint of a skeleton is its first joint, whatever its name
        if hit is None:
            missing.append(role)
        else:
            found[role] = hit
    if missing:
        got = ", ".join(f"{r}={names[j]}" for r, j in found.items()) or "none"
        msg = (f"no joint found for role(s) {', '.join(missing)} (found: {got}); the skeleton has {len(names)} "
               f"joints: {', '.join(names)}. Pass mapping={{role: joint_name}} (gesturedb build --joint-map) "
               "to choose them")
        if source is not None:
            raise InputFileError(source, msg)
        raise ParameterError(msg)
    return found
