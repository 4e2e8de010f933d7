"""What every evaluation shares: the systems, the joints measured and how positions are centred."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from gesturedb.errors import InputFileError
from gesturedb.synth import methods
from gesturedb.synth.inputs import speech_samples
from gesturedb.synth.options import SearchOptions

#: The evaluation's baselines (:mod:`gesturedb.eval.baselines`): windows chosen without the search.
BASELINES = ("random", "pose_only", "audio_only")

#: Systems of the objective evaluation, in table order: the ground truth, the baselines, then what every
#: registered synthesis method contributes (:func:`gesturedb.synth.methods.eval_systems`).
SYSTEMS = ("ground_truth", *BASELINES, *(s.name for s in methods.eval_systems()))

SYSTEM_LABELS = {
    "reference": "database motion (reference)",
    "ground_truth": "ground truth",
    "random": "random windows (mismatched audio)",
    "pose_only": "pose-only matching",
    "audio_only": "audio-only matching",
    **{s.name: s.label for s in methods.eval_systems()},
    "ranksum_refined": "rank-sum + cGAN refiner",
}


def eval_options(options: SearchOptions | None = None, **changes) -> SearchOptions:
    """The search options an evaluation shares across its systems: ``options`` (default: no keyword
    sub-databases, the evaluation compares the search itself) with ``changes``."""
    if options is None:
        options = SearchOptions(keywords=False)
    return SearchOptions.of(options, **changes)


def feature_joint_indices(db) -> dict[str, int]:
    """role -> joint index of the database's feature joints (``db.feature_joints`` holds names)."""
    names = list(db.joint_names)
    out = {}
    for role, name in db.feature_joints.items():
        if name not in names:
            raise InputFileError(db.path, f"feature_joints: role {role!r} names joint {name!r}, which the skeleton lacks")
        out[role] = names.index(name)
    return out


def upper_body_joints(parents: Sequence[int], *, root: int, hips: Sequence[int]) -> np.ndarray:
    """Every joint except the root and the subtrees below the hips.

    Parameters
    ----------
    parents : sequence of int [length J]
        Parent of each joint (-1 for the root), parents before children.
    root : int
    hips : sequence of int
        The joints that start the legs (``left_hip``, ``right_hip``).

    Returns
    -------
    ndarray [shape=(K,)], int64, ascending
    """
    parents = np.asarray(parents, dtype=np.int64)
    leg = np.zeros(parents.shape[0], dtype=bool)
    leg[list(hips)] = True
    for j in range(parents.shape[0]):  # parents come first, so one pass marks whole subtrees
        if parents[j] >= 0 and leg[parents[j]]:
            leg[j] = True
    keep = ~leg
    keep[root] = False
    return np.flatnonzero(keep)


def metric_positions(positions: np.ndarray, root: int) -> np.ndarray:
    """Joint positions with the root's horizontal (x, z) position removed in every frame.

    Parameters
    ----------
    positions : ndarray [shape=(T, J, 3)], metres
    root : int

    Returns
    -------
    ndarray [shape=(T, J, 3)], float64, metres; heights unchanged.
    """
    pos = np.array(positions, dtype=np.float64)
    pos[:, :, 0] -= pos[:, root:root + 1, 0]
    pos[:, :, 2] -= pos[:, root:root + 1, 2]
    return pos


def _centred(positions: np.ndarray, root: int) -> np.ndarray:
    """For display: move the root's horizontal position at frame 0 to the origin."""
    pos = np.array(positions, dtype=np.float64)
    pos[:, :, [0, 2]] -= pos[0, root, [0, 2]]
    return pos


def json_clean(v):
    """Plain JSON types: numpy scalars to Python, NaN/inf to None, recursively through dicts and lists."""
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: json_clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [json_clean(x) for x in v]
    if isinstance(v, np.ndarray):
        return json_clean(v.tolist())
    return v


def _stats(x: np.ndarray) -> tuple[float, float]:
    x = np.asarray(x, dtype=np.float64)
    return float(x.mean()), float(x.std())


def _fmt(v, spec: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


def _read_samples(db, audio, sr):
    """Speech at the database's analysis rate (:func:`gesturedb.synth.inputs.speech_samples`, resampled)."""
    return speech_samples(db, audio, sr, resample=True)
