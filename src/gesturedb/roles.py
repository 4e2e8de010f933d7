"""The one registry of joint roles: which joints are the wrists, the body frame, the arms, the head...

Every stage that names body parts reads them here; this module imports nothing, so the
features, the readers in `gesturedb.io`, retargeting and the evaluation (stages that may not
import one another) all can. Two vocabularies:

- **Roles** (``left_wrist``, ``root``, ...): the few joints the features need, found in any
  rig by name with :func:`gesturedb.io.joints.find_joints` (``gesturedb build --joint-map``
  overrides them). `FEATURE_ROLES`, `BODY_ROLES`, `WRIST_ROLES`, `HIP_ROLES`; `ROLES` is all.
- **Body-part keys** (``left_forearm``, ``head``, ``left_index1``, ...): what
  :func:`gesturedb.io.joints.body_keys` calls every joint of a rig. `JOINT_GROUPS` gathers
  them into the groups the evaluation measures (arms, hands, head, legs, root);
  :func:`gesturedb.io.joints.group_joints` gives their joint indices in a skeleton.
"""
from __future__ import annotations

__all__ = ["BODY_ROLES", "FEATURE_ROLES", "FINGERS", "HIP_ROLES", "JOINT_GROUPS", "RETARGET_REQUIRED", "ROLES",
           "STROKE_JOINT_GROUPS", "WRIST_ROLES"]

# --- roles: joints found by name (gesturedb.io.joints.find_joints) ---------------------------

#: The wrists: speed, height and rhythm of the hands (features.controls, .rhythm, .style).
WRIST_ROLES: tuple[str, ...] = ("left_wrist", "right_wrist")
#: The hip joints (tops of the thighs): the body frame, the legs below them.
HIP_ROLES: tuple[str, ...] = ("left_hip", "right_hip")
#: The 8 pose-feature joints, in the order their coordinates appear in the feature
#: (gesturedb.features.pose): changing it changes every database's pose features.
FEATURE_ROLES: tuple[str, ...] = WRIST_ROLES + ("left_elbow", "right_elbow", "left_index1", "right_index1",
                                                "left_pinky1", "right_pinky1")
#: The joints that define the body frame (gesturedb.features.body.body_frame): its origin and facing.
BODY_ROLES: tuple[str, ...] = ("root",) + HIP_ROLES + ("left_shoulder", "right_shoulder")
#: Every role a database stores (``gesturedb build --joint-map`` may name any of them).
ROLES: tuple[str, ...] = FEATURE_ROLES + BODY_ROLES

# --- groups of body-part keys (gesturedb.io.joints.body_keys) --------------------------------

#: Finger names of body-part keys (``left_index1``...): a joint whose key holds one is a finger joint.
FINGERS: tuple[str, ...] = ("thumb", "index", "middle", "ring", "pinky")

#: Body-part keys of each joint group, in the order tables show the groups; ``None``: every
#: finger joint (`FINGERS`). The jerk of each group is reported (gesturedb.eval.placement).
JOINT_GROUPS: dict[str, tuple[str, ...] | None] = {
    "root": ("hips",),
    "legs": ("left_upleg", "right_upleg", "left_leg", "right_leg", "left_foot", "right_foot", "left_toe", "right_toe"),
    "arms": ("left_upperarm", "left_forearm", "left_hand", "right_upperarm", "right_forearm", "right_hand"),
    "hands": None,
    "head": ("neck", "head"),
}

#: The groups whose frequency bands the stroke tables compare (gesturedb.eval.strokes): the arms
#: without the upper arms, which barely move in a beat stroke, the fingers and the head.
STROKE_JOINT_GROUPS: dict[str, tuple[str, ...] | None] = {
    "arms": ("left_forearm", "right_forearm", "left_hand", "right_hand"),
    "hands": JOINT_GROUPS["hands"],
    "head": JOINT_GROUPS["head"],
}

#: Body parts a source and a target rig must both have for a retarget to mean anything
#: (gesturedb.retarget): the arms carry the gestures.
RETARGET_REQUIRED: tuple[str, ...] = JOINT_GROUPS["arms"]
