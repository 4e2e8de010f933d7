"""Per-frame features, segmentation and clip signatures.

Everything here is plain numpy on plain arrays (librosa for the MFCCs, scipy for
the prominence of speed minima), with keyword-only options, so the readers and
the database builder can be changed independently of the features.

Joint indices come as a dict ``joints: {role: index}``; the roles are
:data:`FEATURE_ROLES` (the 8 pose-feature joints) and :data:`BODY_ROLES` (root,
hips, shoulders: the body frame). Positions are world ``(F, J, 3)`` metres, y up.

| module | what |
|---|---|
| :mod:`.body` | body frame (root origin, yaw from hips + shoulders), speeds |
| :mod:`.pose` | 96-value pose feature of the motion-matching search |
| :mod:`.audio` | 13 MFCCs + log energy per motion frame, deltas |
| :mod:`.segments` | fixed chunks, word-gap clips |
| :mod:`.rhythm` | 32-bit rhythm signatures of speech and motion, Hamming distance |
| :mod:`.style` | style signature (speed, radius, height) |
| :mod:`.controls` | per-frame control signals for control masks |
"""
from __future__ import annotations

from gesturedb.features.audio import audio_deltas, audio_features, n_frames_for_duration
from gesturedb.features.body import BODY_ROLES, body_frame, point_speeds, to_body_frame
from gesturedb.features.controls import CONTROL_DOCS, CONTROL_NAMES, CONTROL_UNITS, control_features
from gesturedb.features.pose import FEATURE_ROLES, pose_feature_size, pose_features
from gesturedb.features.rhythm import audio_rhythm, hamming, hand_speed, motion_rhythm, speed_minima
from gesturedb.features.segments import Clips, fixed_chunks, word_gap_clips
from gesturedb.features.style import STYLE_NAMES, STYLE_UNITS, style_signature, style_signatures

__all__ = [
    "BODY_ROLES",
    "FEATURE_ROLES",
    "CONTROL_NAMES",
    "CONTROL_UNITS",
    "CONTROL_DOCS",
    "STYLE_NAMES",
    "STYLE_UNITS",
    "Clips",
    "body_frame",
    "to_body_frame",
    "point_speeds",
    "pose_features",
    "pose_feature_size",
    "audio_features",
    "audio_deltas",
    "n_frames_for_duration",
    "fixed_chunks",
    "word_gap_clips",
    "audio_rhythm",
    "hand_speed",
    "speed_minima",
    "motion_rhythm",
    "hamming",
    "style_signature",
    "style_signatures",
    "control_features",
]
