"""find_joints across naming schemes, the foreign BVH without fingers, and mapping overrides."""
from __future__ import annotations

import pytest

from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io import BODY_ROLES, FEATURE_ROLES, find_joints, read_bvh
from gesturedb.io.smplx import smplx_skeleton

ALL = FEATURE_ROLES + BODY_ROLES


def _named(names, found):
    return {role: names[j] for role, j in found.items()}


def test_smplx_skeleton():
    names = smplx_skeleton().names
    got = _named(names, find_joints(names))
    assert got == {
        "left_wrist": "left_wrist", "right_wrist": "right_wrist", "left_elbow": "left_elbow",
        "right_elbow": "right_elbow", "left_index1": "left_index1", "right_index1": "right_index1",
        "left_pinky1": "left_pinky1", "right_pinky1": "right_pinky1", "root": "pelvis",
        "left_hip": "left_hip", "right_hip": "right_hip",
        # SMPL-X: left_shoulder is the shoulder joint (left_collar is the clavicle)
        "left_shoulder": "left_shoulder", "right_shoulder": "right_shoulder",
    }


def _scheme(left, right, root, spine):
    """Names for one rig: ``left``/``right`` map part -> joint name."""
    names = [root, spine] + [left[k] for k in left] + [right[k] for k in right]
    want = {"root": root}
    for side, parts in (("left", left), ("right", right)):
        for role_part in ("wrist", "elbow", "index1", "pinky1", "hip", "shoulder"):
            want[f"{side}_{role_part}"] = parts[role_part]
    return names, want


def _sides(fmt, parts, distractors=()):
    left = {k: fmt(v, "Left", "l", "L") for k, v in parts.items()}
    right = {k: fmt(v, "Right", "r", "R") for k, v in parts.items()}
    for d in distractors:
        left[f"x_{d}"] = fmt(d, "Left", "l", "L")
        right[f"x_{d}"] = fmt(d, "Right", "r", "R")
    return left, right


SCHEMES = {
    "genea": (lambda v, word, s, S: f"b_{s}_{v}",
              {"wrist": "wrist", "elbow": "forearm", "index1": "index1", "pinky1": "pinky1", "hip": "upleg",
               "shoulder": "arm"},
              ("shoulder", "arm_twist", "wrist_twist", "index2", "thumb0"), "b_root", "b_spine0"),
    "zeggs": (lambda v, word, s, S: f"{word}{v}",
              {"wrist": "Hand", "elbow": "ForeArm", "index1": "HandIndex1", "pinky1": "HandPinky1", "hip": "UpLeg",
               "shoulder": "Arm"},
              ("Shoulder", "HandIndex2", "HandThumb1", "Leg"), "Hips", "Spine"),
    "mixamo": (lambda v, word, s, S: f"mixamorig:{word}{v}",
               {"wrist": "Hand", "elbow": "ForeArm", "index1": "HandIndex1", "pinky1": "HandPinky1",
                "hip": "UpLeg", "shoulder": "Arm"},
               ("Shoulder", "HandIndex4", "Leg"), "mixamorig:Hips", "mixamorig:Spine"),
    "generic": (lambda v, word, s, S: f"{word}{v}",
                {"wrist": "Wrist", "elbow": "Elbow", "index1": "Index1", "pinky1": "Little1", "hip": "Hip",
                 "shoulder": "Shoulder"},
                ("Collar", "Knee"), "Hips", "Chest"),
    "cmu": (lambda v, word, s, S: f"{S}{v}" if v.endswith("Joint") else f"{word}{v}",
            {"wrist": "Hand", "elbow": "ForeArm", "index1": "HandIndex1", "pinky1": "HandPinky1", "hip": "UpLeg",
             "shoulder": "Arm"},
            ("HipJoint",), "Hips", "LowerBack"),
    "snake_upper": (lambda v, word, s, S: f"{word.upper()}_{v.upper()}",
                    {"wrist": "wrist", "elbow": "elbow", "index1": "index_01", "pinky1": "pinky_01", "hip": "thigh",
                     "shoulder": "upper_arm"},
                    ("clavicle",), "ROOT", "SPINE_01"),
    "suffix": (lambda v, word, s, S: f"{v}.{S}",
               {"wrist": "hand", "elbow": "forearm", "index1": "finger_index_01", "pinky1": "finger_little_01",
                "hip": "thigh", "shoulder": "upper_arm"},
               ("shoulder",), "pelvis", "spine"),
}


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_naming_schemes(scheme):
    fmt, parts, distractors, root, spine = SCHEMES[scheme]
    left, right = _sides(fmt, parts, distractors)
    names, want = _scheme({k: v for k, v in left.items() if not k.startswith("x_")},
                          {k: v for k, v in right.items() if not k.startswith("x_")}, root, spine)
    # distractors (clavicles, twist bones, further finger segments) go first, where a sloppy match would land
    names = [root] + [v for k, v in left.items() if k.startswith("x_")] + \
        [v for k, v in right.items() if k.startswith("x_")] + names[1:]
    assert _named(names, find_joints(names)) == want


def test_case_and_separators_do_not_matter():
    names = ["HIPS", "left-hand", "RIGHT_HAND", "Left Fore Arm", "right.forearm"]
    got = _named(names, find_joints(names, ("root", "left_wrist", "right_wrist", "left_elbow", "right_elbow")))
    assert got == {"root": "HIPS", "left_wrist": "left-hand", "right_wrist": "RIGHT_HAND",
                   "left_elbow": "Left Fore Arm", "right_elbow": "right.forearm"}


def test_wrist_preferred_over_hand_and_root_falls_back_to_joint_0():
    names = ["Reference", "LeftWrist", "LeftHand"]
    assert _named(names, find_joints(names, ("root", "left_wrist"))) == {"root": "Reference", "left_wrist": "LeftWrist"}


def test_foreign_bvh_without_fingers(data_dir):
    path = data_dir / "bvh-foreign" / "AV_8Walk_Meredith_HVHA_Rep1.bvh"
    names = read_bvh(path).skeleton.names
    with pytest.raises(InputFileError) as err:
        find_joints(names, source=path)
    msg = str(err.value)
    assert msg.startswith(str(path) + ": no joint found for role(s) left_index1, right_index1, left_pinky1, "
                                      "right_pinky1")
    assert "left_wrist=LeftHand" in msg and "left_shoulder=LeftArm" in msg
    assert all(n in msg for n in names)  # every joint of the file is listed
    mapping = {"left_index1": "LeftHandThumb1", "right_index1": "RightHandThumb1",
               "left_pinky1": "LeftHand_End", "right_pinky1": "RightHand_End"}
    got = _named(names, find_joints(names, mapping=mapping, source=path))
    assert got["left_index1"] == "LeftHandThumb1" and got["right_pinky1"] == "RightHand_End"
    assert got["left_wrist"] == "LeftHand" and got["root"] == "Hips" and got["left_hip"] == "LeftUpLeg"
    # only the roles asked for are needed
    assert set(find_joints(names, BODY_ROLES)) == set(BODY_ROLES)


def test_mapping_overrides_a_match_and_is_checked():
    names = smplx_skeleton().names
    got = find_joints(names, ("left_wrist",), mapping={"left_wrist": "left_index1"})
    assert got == {"left_wrist": names.index("left_index1")}
    with pytest.raises(ParameterError, match=r"mapping\['left_wrist'\]: no joint named 'LeftHand'; joints: pelvis"):
        find_joints(names, mapping={"left_wrist": "LeftHand"})
    with pytest.raises(ParameterError, match="roles: unknown 'left_thumb'; known roles: left_wrist"):
        find_joints(names, ("left_thumb",))
    with pytest.raises(ParameterError, match="roles: unknown 'nose'"):
        find_joints(names, mapping={"nose": "head"})


def test_missing_role_without_source_is_a_parameter_error():
    want = r"no joint found for role\(s\) right_wrist \(found: left_wrist=LeftHand\); the skeleton has 2 joints: Hips"
    with pytest.raises(ParameterError, match=want):
        find_joints(["Hips", "LeftHand"], ("left_wrist", "right_wrist"))


# --- issue 41: joint maps with a BOM, messages of bounded length --------------------------------------------

def test_a_map_of_many_unknown_keys_is_refused_fast_in_one_short_line():
    """Such a map printed 23 MB (and checked each key against a growing list); now the first keys and
    the count, in well under a second of work."""
    import time

    names = smplx_skeleton().names
    mapping = {f"bogus_{i}": "pelvis" for i in range(300_000)}  # the issue had 2M; the old check was quadratic
    t0 = time.perf_counter()
    with pytest.raises(ParameterError, match=r"^roles: unknown 'bogus_0', 'bogus_1', .*'bogus_11', \.\.\. "
                                             r"\(300000 in all\); known roles: left_wrist, ") as err:
        find_joints(names, mapping=mapping)
    assert time.perf_counter() - t0 < 10.0
    assert len(str(err.value)) < 600 and "\n" not in str(err.value)


def test_joint_lists_and_names_in_messages_are_capped():
    names = ["Hips"] + [f"j{i}_" + "x" * 200 for i in range(5_000)]
    with pytest.raises(InputFileError, match=r"the skeleton has 5001 joints: Hips, j0_x{77}\.\.\. \(203 characters\), "
                                             r".*\.\.\. \(5001 in all\)\. Pass mapping") as err:
        find_joints(names, ("left_wrist",), source="rig.bvh")
    assert len(str(err.value)) < 80 * 110
    with pytest.raises(ParameterError, match=r"^mapping\['left_wrist'\]: no joint named 'y{80}'\.\.\. "
                                             r"\(100000 characters\); joints: Hips, ") as err:
        find_joints(names, ("left_wrist",), mapping={"left_wrist": "y" * 100_000})
    assert len(str(err.value)) < 80 * 110


def test_read_joint_map_takes_text_or_a_file_with_or_without_a_bom(tmp_path):
    from gesturedb.io.joints import read_joint_map

    want = {"left_index1": "LeftHandThumb1", "root": "Hips"}
    text = '{"left_index1": "LeftHandThumb1", "root": "Hips"}'
    assert read_joint_map(text) == want and read_joint_map(None) is None
    for name, data in (("plain.json", text.encode()), ("bom.json", b"\xef\xbb\xbf" + text.encode()),
                       ("bom16.json", text.encode("utf-8-sig"))):
        (tmp_path / name).write_bytes(data)
        assert read_joint_map(str(tmp_path / name)) == want, name
    bad = tmp_path / "bad.json"
    bad.write_text('{"left_wrist": ')
    with pytest.raises(InputFileError, match=rf"^{bad}: --joint-map: expected a JSON object \{{role: joint name\}} "
                                             r"or a \.json file holding one; got invalid JSON \(Expecting value"):
        read_joint_map(str(bad))
    bad.write_text('["left_wrist"]')
    with pytest.raises(InputFileError, match=rf"^{bad}: --joint-map: expected a JSON object \{{role: joint name\}}; "
                                             r"got list$"):
        read_joint_map(str(bad))
    with pytest.raises(ParameterError, match=r"^--joint-map: expected a JSON object .* got '\{x{79}'\.\.\. "
                                             r"\(100002 characters\) \("):
        read_joint_map("{" + "x" * 100_000 + "}")
    with pytest.raises(ParameterError, match=r"^--joint-map: \['root'\]: expected a joint name \(a string\); got 3$"):
        read_joint_map('{"root": 3}')
    big = tmp_path / "big.json"
    big.write_text("{" + " " * (1 << 20) + "}")
    with pytest.raises(InputFileError, match=r"--joint-map: expected a JSON object of at most 1048576 bytes"):
        read_joint_map(str(big))


def test_joint_roles_have_one_home():
    """gesturedb.roles is the only module that spells a collection of role names or body-part keys:
    the features, io, retargeting and eval read it (a second copy drifts: three did)."""
    import ast
    from pathlib import Path

    import gesturedb
    from gesturedb import roles
    from gesturedb.eval import placement, strokes
    from gesturedb.features import body, pose

    assert pose.FEATURE_ROLES is roles.FEATURE_ROLES and body.BODY_ROLES is roles.BODY_ROLES
    assert FEATURE_ROLES is roles.FEATURE_ROLES and BODY_ROLES is roles.BODY_ROLES
    assert placement.JOINT_GROUPS is roles.JOINT_GROUPS and strokes.STROKE_GROUPS == tuple(roles.STROKE_JOINT_GROUPS)
    vocab = set(roles.ROLES) | set(roles.FINGERS) | {k for g in (roles.JOINT_GROUPS, roles.STROKE_JOINT_GROUPS)
                                                     for keys in g.values() if keys for k in keys}
    pkg = Path(gesturedb.__file__).parent
    copies = []
    for path in sorted(pkg.rglob("*.py")):
        if path == pkg / "roles.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and len(node.elts) >= 2 and all(
                    isinstance(e, ast.Constant) and e.value in vocab for e in node.elts):
                copies.append(f"{path.relative_to(pkg)}:{node.lineno}: {[e.value for e in node.elts]}")
    assert copies == [], "joint roles spelled outside gesturedb/roles.py:\n" + "\n".join(copies)


def test_group_joints_on_real_rigs(scott_dir, data_dir):
    from gesturedb.io import read_smplx
    from gesturedb.io.joints import body_keys, group_joints
    from gesturedb.roles import JOINT_GROUPS, STROKE_JOINT_GROUPS

    names = read_smplx(scott_dir / "2_scott_0_1_1.npz").skeleton.names
    g = group_joints(names)
    assert list(g) == list(JOINT_GROUPS)  # SMPL-X has every group, in table order
    keys = body_keys(names)
    assert sorted(keys[j] for j in g["head"]) == ["head", "neck"]
    assert len(g["hands"]) == 30 and len(g["arms"]) == 6 and len(g["legs"]) == 8  # 15 finger joints a hand
    assert set(group_joints(names, STROKE_JOINT_GROUPS)["arms"]) < set(g["arms"])
    # another pipeline's BVH: a thumb stub per hand, no neck, toes
    foreign = read_bvh(data_dir / "bvh-foreign" / "AV_8Walk_Meredith_HVHA_Rep1.bvh").skeleton.names
    g = {k: [foreign[j] for j in v] for k, v in group_joints(foreign).items()}
    assert g["hands"] == ["LeftHandThumb1", "RightHandThumb1"] and g["head"] == ["Head"]
    assert g["arms"] == ["LeftArm", "LeftForeArm", "LeftHand", "RightArm", "RightForeArm", "RightHand"]
    assert len(g["legs"]) == 8 and g["root"] == ["Hips"]
