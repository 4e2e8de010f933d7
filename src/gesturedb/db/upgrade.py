"""Bring a database written under an older schema to the current one (`gesturedb upgrade DB.h5`).

What each version lacks, and what the upgrade recomputes from what the file keeps:

* before 4: the pose features stacked the past only (frames f, f-2, f-4, f-6); they are
  recomputed, centred on each frame (:func:`gesturedb.features.pose.pose_features`), from the
  stored joint positions with the file's frame rate and the stride a build chooses from the
  motion's timescale (:func:`gesturedb.features.pose.timescale_pose_stride`), and the ``config``
  records the new ``pose_window`` and ``pose_stride``. At a frame rate other than 15 fps the control
  features are recomputed too (their facing smoothing is now in seconds), with the default
  masks; saved masks keep their frames.
* before 5: the pose features had no stance; they are recomputed with the ankles
  (:func:`gesturedb.io.joints.ankle_joints`; a rig without legs keeps the 8 feature joints)
  from the stored joint positions, as a build of this version computes them.
* before 3: no lower-body graph (and, before 2, no graph at all): both motion graphs and the
  style predictor are computed as a build makes them.

The features are the bits a build of this version writes (it computes them from the same
float32 positions). The upgrade goes through :func:`gesturedb.db.storage.edit`: a temporary
copy, renamed over the file on success. A sharded database is upgraded by rebuilding it, or by
upgrading the single file it was sharded from and sharding that again.
"""
from __future__ import annotations

import os

import numpy as np

from gesturedb.db import schema, storage, store
from gesturedb.db.cluster import optional_client
from gesturedb.db.edit import add_control_features
from gesturedb.db.graph import write_graph
from gesturedb.errors import InputFileError, SchemaError
from gesturedb.features.body import BODY_ROLES
from gesturedb.features.pose import (
    POSE_WINDOW,
    motion_timescale,
    pose_features,
    timescale_pose_stride,
    velocity_lag_products,
)
from gesturedb.io.joints import ankle_joints, find_joints
from gesturedb.roles import FEATURE_ROLES

__all__ = ["upgrade", "file_version"]

#: the first version whose pose features are centred on the frame
CENTRED_POSE_VERSION = 4
#: the first version whose pose features carry the ankles (the stance)
STANCE_POSE_VERSION = 5


def file_version(path: str | os.PathLike) -> int:
    """The ``schema_version`` a database file was written with: the current one or one that
    :func:`upgrade` upgrades (anything else is a :class:`SchemaError` naming the file)."""
    import h5py  # lazily, as everywhere in db/: `import gesturedb` stays light

    name = os.fspath(path)
    if not os.path.isfile(name):
        raise InputFileError(name, "no such file")
    try:
        h5 = h5py.File(name, "r")
    except OSError as exc:
        raise InputFileError(name, f"not an HDF5 file ({exc})") from None
    with h5:
        got = schema.check_version(h5, name, upgradable=True)
        if got != schema.SCHEMA_VERSION and schema.SHARDS_ATTR in h5.attrs:
            # the frames are in the shard files, each a part of one database: upgrading them one by one
            # could leave a mix of versions; the single file they came from is upgraded in one edit
            raise SchemaError(name, f"{schema.SHARDS_ATTR}: this is the index of a sharded database of schema "
                                    f"{got}; upgrade the single database it was sharded from (`gesturedb upgrade "
                                    f"DB.h5`) and shard it again (`gesturedb shard`), or rebuild it")
        return got


def upgrade(path: str | os.PathLike, *, progress: bool = False, scheduler=None) -> dict:
    """Upgrade the database file at ``path`` in place to :data:`schema.SCHEMA_VERSION`.

    Returns ``{"from": version, "to": version, "done": [what was recomputed, ...]}``; a file
    already current is left untouched (``done`` empty). ``progress`` and ``scheduler``: as
    for :func:`gesturedb.db.graph.write_graph` (only used when the graphs are recomputed).
    """
    got = file_version(path)
    if got == schema.SCHEMA_VERSION:
        return {"from": got, "to": got, "done": []}
    done = []
    with optional_client(scheduler) as client:
        with storage.edit(path, upgrade=True) as h5:
            if got < STANCE_POSE_VERSION:
                _recompute_pose_features(h5, os.fspath(path))
                done.append("pose features centred on each frame, with the stance"
                            if got < CENTRED_POSE_VERSION else "pose features with the stance (the ankles)")
            if got < 3:
                for grp in (*schema.GRAPHS, schema.STYLE_MODEL):
                    store.delete(h5, grp)
                write_graph(h5, progress=progress, scheduler=client)
                done.append("upper- and lower-body motion graphs and style predictor")
            store.set_attrs(h5, "", {"schema_version": schema.SCHEMA_VERSION})
            fps = float(store.attrs(h5)["fps"])
    if got < CENTRED_POSE_VERSION and fps != 15.0:
        add_control_features(path)  # an edit of its own: the file is current now
        done.append("control features (facing smoothing in seconds) and their default masks")
    return {"from": got, "to": schema.SCHEMA_VERSION, "done": done}


def _recompute_pose_features(h5, name: str) -> None:
    attrs = store.attrs(h5)
    fps = float(attrs["fps"])
    config = schema.read_json_attr(h5, "config", {})
    mapping = schema.read_json_attr(h5, "feature_joints", {}) or None
    names = schema.read(h5, schema.SKELETON_NAMES)
    joints = find_joints(names, FEATURE_ROLES + BODY_ROLES, mapping=mapping, source=name)
    starts = schema.read(h5, schema.RECORDING_START_FRAME)
    counts = schema.read(h5, schema.RECORDING_N_FRAMES)
    positions = store.array(h5, schema.JOINT_POSITIONS)
    spans = list(zip(starts.tolist(), counts.tolist()))

    def recording(a, n):
        return np.asarray(positions[a:a + n], dtype=np.float32).astype(np.float64)

    # the stride a build of this version chooses: from the whole database's motion
    lags = sum(velocity_lag_products(recording(a, n), joints=joints, fps=fps) for a, n in spans)
    timescale = motion_timescale(lags, fps) if spans else None
    stride = timescale_pose_stride(timescale, fps)
    ankles = ankle_joints(names)
    parts = [pose_features(recording(a, n), joints=joints, fps=fps, window=POSE_WINDOW, stride=stride,
                           stance=ankles) for a, n in spans]
    pose = np.concatenate(parts) if parts else np.zeros((0, 0), np.float32)
    if pose.shape[0] != positions.shape[0]:
        raise SchemaError(name, f"recordings: expected them to cover the {positions.shape[0]} frames of "
                                f"{schema.JOINT_POSITIONS}, got {pose.shape[0]}")
    store.delete(h5, schema.POSE_FEATURES)
    schema.write(h5, schema.POSE_FEATURES, pose, {})
    schema.write_json_attr(h5, "config", {**config, "pose_window": POSE_WINDOW, "pose_stride": stride})
    if timescale is not None:
        store.set_attrs(h5, "", {"motion_timescale_s": timescale})
