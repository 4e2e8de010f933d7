"""Hand-made motion for the feature tests (helpers only, no tests here).

A standing speaker with SMPL-X joint indices and plausible bone lengths, whose
arms move along known smooth curves, plus rigid yaw/translation transforms.
Imported by the other tests/test_features_*.py files.
"""
from __future__ import annotations

import numpy as np

#: Roles -> SMPL-X joint indices (see ../shared/data/README.md).
SMPLX_JOINTS = {
    "root": 0,
    "left_hip": 1,
    "right_hip": 2,
    "left_shoulder": 16,
    "right_shoulder": 17,
    "left_elbow": 18,
    "right_elbow": 19,
    "left_wrist": 20,
    "right_wrist": 21,
    "left_index1": 25,
    "left_pinky1": 31,
    "right_index1": 40,
    "right_pinky1": 46,
}

N_JOINTS = 55
PELVIS_Y = 0.95


def rest_positions() -> np.ndarray:
    """(55, 3) rest pose facing +z, +x the speaker's left, y up, metres."""
    p = np.zeros((N_JOINTS, 3))
    p[:] = (0.0, PELVIS_Y, 0.0)
    j = SMPLX_JOINTS
    for side, s in (("left", 1.0), ("right", -1.0)):
        p[j[f"{side}_hip"]] = (0.09 * s, 0.88, 0.0)
        p[j[f"{side}_shoulder"]] = (0.18 * s, 1.42, 0.0)
        p[j[f"{side}_elbow"]] = (0.22 * s, 1.15, 0.05)
        p[j[f"{side}_wrist"]] = (0.20 * s, 1.02, 0.28)
        p[j[f"{side}_index1"]] = (0.19 * s, 1.00, 0.37)
        p[j[f"{side}_pinky1"]] = (0.23 * s, 1.00, 0.35)
    return p


def yaw_matrix(angle: float) -> np.ndarray:
    """Rotation about +y by ``angle`` radians; maps +z to (sin, 0, cos)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def gesturing(n_frames: int = 240, fps: float = 30.0, seed: int = 0) -> np.ndarray:
    """(F, 55, 3) standing speaker facing +z whose forearms and hands move smoothly.

    Each side's elbow, wrist and finger roots move together with a sum of random
    low-frequency sinusoids (a few cm, about 0.1 to 1 m/s), the wrist with an
    extra independent motion, the torso stays put.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / fps
    pos = np.repeat(rest_positions()[None], n_frames, axis=0)
    j = SMPLX_JOINTS
    for side in ("left", "right"):
        arm = np.zeros((n_frames, 3))
        hand = np.zeros((n_frames, 3))
        for _ in range(3):
            amp = rng.uniform(0.01, 0.05, 3)
            freq = rng.uniform(0.3, 1.5, 3)
            phase = rng.uniform(0, 2 * np.pi, 3)
            arm += amp * np.sin(2 * np.pi * freq * t[:, None] + phase)
            amp = rng.uniform(0.01, 0.06, 3)
            freq = rng.uniform(0.5, 2.0, 3)
            phase = rng.uniform(0, 2 * np.pi, 3)
            hand += amp * np.sin(2 * np.pi * freq * t[:, None] + phase)
        pos[:, j[f"{side}_elbow"]] += arm
        for name in ("wrist", "index1", "pinky1"):
            pos[:, j[f"{side}_{name}"]] += arm + hand
    return pos


def rigid(positions: np.ndarray, angles, translations) -> np.ndarray:
    """Rotate frame f about the world y axis through the origin by ``angles[f]``
    (scalar for all frames) and then add ``translations[f]`` ((3,) for all)."""
    positions = np.asarray(positions, dtype=np.float64)
    n = len(positions)
    angles = np.broadcast_to(np.asarray(angles, dtype=np.float64), (n,))
    translations = np.broadcast_to(np.asarray(translations, dtype=np.float64), (n, 3))
    mats = np.stack([yaw_matrix(a) for a in angles])
    return np.einsum("fij,fkj->fki", mats, positions) + translations[:, None, :]
