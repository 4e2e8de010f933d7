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

import functools
import json
import os
import re

import numpy as np

from gesturedb.errors import InputFileError, ParameterError, echo, echo_list
from gesturedb.roles import BODY_ROLES, FEATURE_ROLES, FINGERS, HIP_ROLES, JOINT_GROUPS, ROLES

__all__ = ["BODY_ROLES", "FEATURE_ROLES", "ankle_joints", "body_keys", "find_joints", "group_joints", "leg_joints",
           "read_joint_map"]

#: joint names a message lists before it counts the rest (a body with fingers has about 70)
MESSAGE_JOINTS = 80
#: largest joint-map file read: a map has at most a dozen roles
MAX_JOINT_MAP_BYTES = 1 << 20

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


def find_joints(names, roles=ROLES, *, mapping=None, source=None) -> dict[str, int]:
    """Map roles to joint indices by name.

    Parameters
    ----------
    names : sequence of str [length J]
        Joint names, e.g. ``Skeleton.names`` (index 0 is the root).
    roles : sequence of str
        Roles to find, from `gesturedb.roles.ROLES` (`FEATURE_ROLES` and `BODY_ROLES`).
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
    known = ROLES
    roles = tuple(roles)
    unknown = list(dict.fromkeys(r for r in roles if r not in known))
    mapping = dict(mapping or {})
    # a set, not a scan of the list per key: a map of 2M unknown keys is refused in a second
    seen = set(unknown)
    unknown += [r for r in mapping if r not in known and r not in seen]
    if unknown:
        raise ParameterError(f"roles: unknown {echo_list(unknown, quote=True)}; known roles: {', '.join(known)}")
    for role, joint in mapping.items():
        if joint not in names:
            raise ParameterError(f"mapping[{echo(role)}]: no joint named {echo(joint)}; joints: "
                                 f"{echo_list(names, MESSAGE_JOINTS)}")

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
        got = echo_list([f"{r}={names[j]}" for r, j in found.items()], len(found)) or "none"
        msg = (f"no joint found for role(s) {', '.join(missing)} (found: {got}); the skeleton has {len(names)} "
               f"joints: {echo_list(names, MESSAGE_JOINTS)}. Pass mapping={{role: joint_name}} "
               "(gesturedb build --joint-map) to choose them")
        if source is not None:
            raise InputFileError(source, msg)
        raise ParameterError(msg)
    return found


def read_joint_map(text) -> dict[str, str] | None:
    """A ``{role: joint name}`` map from JSON text or a ``.json`` file (``gesturedb build --joint-map``).

    Parameters
    ----------
    text : str or None
        The JSON object itself, or the path of a file holding it (UTF-8, a byte-order
        mark allowed: Windows editors write one). ``None`` gives ``None``.

    Returns
    -------
    dict of str to str or None
        Checked against the roles by `find_joints` when it is used.

    Raises
    ------
    InputFileError
        A file that cannot be read, is larger than `MAX_JOINT_MAP_BYTES`, or does not hold
        a JSON object of strings.
    ParameterError
        The same for JSON given as text.
    """
    if text is None:
        return None
    text = os.fspath(text)
    is_file = os.path.isfile(text)
    if is_file:
        def fail(problem):
            raise InputFileError(text, f"--joint-map: {problem}")
        try:
            size = os.path.getsize(text)
            if size > MAX_JOINT_MAP_BYTES:
                fail(f"expected a JSON object of at most {MAX_JOINT_MAP_BYTES} bytes (MAX_JOINT_MAP_BYTES), got {size}")
            with open(text, encoding="utf-8-sig") as f:
                body = f.read()
        except (OSError, UnicodeError) as exc:
            fail(f"cannot read: {exc}")
    else:
        def fail(problem):
            raise ParameterError(f"--joint-map: {problem}")
        body = text
    try:
        doc = json.loads(body.lstrip("\ufeff"))
    except RecursionError:
        fail("invalid JSON: nested too deeply")
    except ValueError as exc:  # json.JSONDecodeError, or a number of more than 4300 digits
        got = "invalid JSON" if is_file else echo(text)
        fail(f"expected a JSON object {{role: joint name}} or a .json file holding one; got {got} "
             f"({str(exc).splitlines()[0]})")
    if not isinstance(doc, dict):
        fail(f"expected a JSON object {{role: joint name}}; got {type(doc).__name__}")
    bad = next(((k, v) for k, v in doc.items() if not isinstance(v, str)), None)
    if bad is not None:
        fail(f"[{echo(bad[0])}]: expected a joint name (a string); got {echo(bad[1])}")
    return doc


# --- whole-skeleton correspondence (retargeting) ------------------------------------------
# Every body part a retargeted joint can carry, side removed, digits kept where they
# number a segment: part name as `_parse` leaves it (digits stripped) -> canonical part.
_BODY_PARTS = {
    "hips": "hips", "pelvis": "hips", "root": "hips",
    "spine": "spine", "chest": "spine", "upperchest": "spine", "torso": "spine", "back": "spine",
    "neck": "neck", "head": "head",
    "collar": "collar", "clavicle": "collar", "scap": "collar",
    "arm": "upperarm", "upperarm": "upperarm", "uparm": "upperarm", "humerus": "upperarm",
    "forearm": "forearm", "lowerarm": "forearm", "elbow": "forearm",
    "hand": "hand", "wrist": "hand",
    "upleg": "upleg", "upperleg": "upleg", "thigh": "upleg", "femur": "upleg",
    "leg": "leg", "lowerleg": "leg", "knee": "leg", "calf": "leg", "shin": "leg",
    "foot": "foot", "ankle": "foot",
    "toebase": "toe", "toe": "toe", "toes": "toe", "ball": "toe",
}
_FINGER_SYNONYMS = {"little": "pinky", "pinkie": "pinky"}
# names that mark a joint as no anatomical joint of its own (End Site stand-ins, twist
# helpers): they keep their rest rotation
_SKIP = ("end", "top", "twist", "roll", "nub", "site", "tip")


def _canonical_part(side, part, has_part) -> str | None:
    """Canonical key of one joint, or None when it is no joint we transfer."""
    if any(s in part for s in _SKIP):
        return None
    digits = re.sub(r"^\D*", "", part)
    stem = re.sub(r"\d+$", "", part)
    # HandIndex, IndexFinger, FingerIndex, Index: the finger's own word is what counts
    for prefix in ("hand", "fingers", "finger"):
        if stem.startswith(prefix) and len(stem) > len(prefix):
            stem = stem[len(prefix):]
    if stem.endswith("finger") and len(stem) > len("finger"):
        stem = stem[:-len("finger")]
    stem = _FINGER_SYNONYMS.get(stem, stem)
    if stem in FINGERS and side is not None:
        return f"{side}_{stem}{int(digits) if digits else 1}"
    if side is None:
        if stem == "hip" or stem == "hips":
            return "hips"
        canon = _BODY_PARTS.get(stem)
        return canon if canon in ("hips", "spine", "neck", "head") else None
    # words whose meaning depends on the rig's other names
    if stem == "shoulder":
        # BVH rigs: Shoulder = clavicle, Arm = upper arm; SMPL-X: collar + shoulder = upper arm
        canon = "collar" if has_part(side, ("arm", "upperarm", "uparm", "humerus")) else "upperarm"
    elif stem == "hip":
        canon = "upleg"
    elif stem == "foot":
        # SMPL-X: ankle + foot (the toes); BVH rigs: Foot + ToeBase
        canon = "toe" if has_part(side, ("ankle",)) else "foot"
    else:
        canon = _BODY_PARTS.get(stem)
    return None if canon is None else f"{side}_{canon}"


def body_keys(names) -> dict[int, str]:
    """Canonical body-part key of every joint that has one.

    Keys are ``hips``, ``spine0``, ``spine1``, ... (the spine chain from the hips
    up, numbered in order), ``neck``, ``head``, and per side ``left_collar``,
    ``left_upperarm``, ``left_forearm``, ``left_hand``, ``left_upleg``,
    ``left_leg``, ``left_foot``, ``left_toe`` and fingers ``left_index1`` ...
    (segment numbers as the rig writes them). They are read from the names of
    SMPL-X, GENEA / Talking With Hands (``b_l_arm``), ZEGGS and Mixamo
    (``mixamorig:LeftArm``), Unreal (``upperarm_l``, ``calf_l``, ``index_01_l``)
    and generic BVH rigs. Where a word means different bones in different
    schemes (``shoulder``: the clavicle in BVH rigs that also have an ``Arm``,
    the upper arm in SMPL-X; ``foot``: the toes when there is an ``ankle``), the
    other names of the rig decide. Twist helpers and End-Site stand-ins
    (``*_twist``, ``HeadTop_End``) get no key. When two joints get the same key
    the one nearer the root (lower index) keeps it.

    Parameters
    ----------
    names : sequence of str [length J]

    Returns
    -------
    dict of int to str
        Joint index -> key, for the joints that have one.
    """
    # a pure function of the names, asked twice per assembled motion (feet, legs):
    # about 3% of assembling a 64-frame window, which the refiner's training data
    # does for every window of the database
    return dict(_body_keys(tuple(str(n) for n in names)))


def ankle_joints(names) -> np.ndarray:
    """The left and the right ankle (body-part keys ``left_foot``, ``right_foot``), (2,) int64.

    The joints the feet are planted by (:func:`gesturedb.synth.contacts.foot_joints`) and whose
    stance the pose features carry (:func:`gesturedb.features.pose.pose_features`). Empty (0,)
    when the rig lacks either: an upper-body rig has no stance.
    """
    keys = {k: j for j, k in body_keys(names).items()}
    ankles = [keys.get("left_foot"), keys.get("right_foot")]
    if None in ankles:
        return np.zeros(0, dtype=np.int64)
    return np.asarray(ankles, dtype=np.int64)


@functools.lru_cache(maxsize=32)
def _body_keys(names: tuple) -> dict[int, str]:
    parsed = [_parse(n) for n in names]
    parts = {(s, re.sub(r"\d+$", "", p)) for s, p in parsed}

    def has_part(side, stems):
        return any((side, s) in parts for s in stems)

    keys: dict[int, str] = {}
    taken = set()
    spine = []
    # the hips: a joint called hips/pelvis, else one called root, else joint 0 (Unreal's
    # "root" sits on the floor below its "pelvis")
    hips = next((j for j, (s, p) in enumerate(parsed) if s is None and p in ("hips", "hip", "pelvis")), None)
    if hips is None:
        hips = next((j for j, (s, p) in enumerate(parsed) if s is None and p == "root"), 0)
    if names:
        keys[hips] = "hips"
        taken.add("hips")
    for j, (side, part) in enumerate(parsed):
        key = _canonical_part(side, part, has_part)
        if key == "hips":
            continue
        if key == "spine":
            spine.append(j)
            continue
        if key is None or key in taken:
            continue
        if key in ("neck",) and "neck" in taken:
            continue
        keys[j] = key
        taken.add(key)
    for i, j in enumerate(spine):
        keys[j] = f"spine{i}"
    return keys


def group_joints(names, groups=JOINT_GROUPS) -> dict[str, np.ndarray]:
    """Joint indices of every group that the skeleton has.

    Parameters
    ----------
    names : sequence of str [length J]
    groups : dict of str to (tuple of str or None)
        Group -> body-part keys (`body_keys`), ``None`` for every finger joint;
        default `gesturedb.roles.JOINT_GROUPS`.

    Returns
    -------
    dict of str to ndarray [shape=(n,)], int64, ascending
        Only the groups with at least one joint, in the order of ``groups``.
    """
    keys = body_keys(names)
    out = {}
    for g, parts in groups.items():
        if parts is None:
            js = [j for j, k in keys.items() if any(f in k for f in FINGERS)]
        else:
            js = [j for j, k in keys.items() if k in parts]
        if js:
            out[g] = np.asarray(sorted(js), dtype=np.int64)
    return out


def leg_joints(names, parents) -> np.ndarray:
    """The joints of both legs: each hip joint (role ``left_hip``/``right_hip``) and everything below it.

    Parameters
    ----------
    names : sequence of str [length J]
    parents : sequence of int [length J], -1 for the root

    Returns
    -------
    ndarray [shape=(L,)], int64, ascending; empty when the rig has no recognisable hips.
    """
    try:
        hips = set(find_joints(names, HIP_ROLES).values())
    except (InputFileError, ParameterError):
        return np.zeros(0, dtype=np.int64)
    parents = [int(p) for p in parents]
    out = []
    for j in range(len(parents)):
        k = j
        while k >= 0 and k not in hips:
            k = parents[k]
        if k >= 0:
            out.append(j)
    return np.asarray(out, dtype=np.int64)
