"""Edits of an existing database: saved masks and control features.

Every edit goes through :func:`gesturedb.db.storage.edit` (copy, edit, rename).
"""
from __future__ import annotations

import os

from gesturedb.db import schema
from gesturedb.db.storage import edit


def add_control_features(path: str | os.PathLike, *, replace: bool = True) -> list[str]:
    """(Re)compute the per-frame control features of a database from its stored joint positions.

    For databases built before a control feature existed, or after changing
    its definition. Each recording is processed on its own (no speed across
    recording boundaries); the 15th/85th-percentile masks are recomputed.

    Returns
    -------
    list of str
        The control features now in the file.
    """
    import numpy as np

    from gesturedb.db.build import write_default_masks
    from gesturedb.db.database import Database
    from gesturedb.features.controls import CONTROL_DOCS, CONTROL_UNITS, control_features
    from gesturedb.io.joints import BODY_ROLES, FEATURE_ROLES, find_joints

    with Database(path) as db:
        names = db.joint_names
        joints = find_joints(names, FEATURE_ROLES + BODY_ROLES,
                             mapping={r: n for r, n in db.feature_joints.items()}, source=db.path)
        parts = [control_features(np.asarray(db.joint_positions[r.start_frame:r.stop_frame], dtype=np.float64),
                                  joints=joints, fps=db.fps) for r in db.recordings]
    controls = {k: np.concatenate([p[k] for p in parts]).astype(np.float32) for k in sorted(parts[0])}
    with edit(path) as h5:
        g = h5.require_group(schema.CONTROLS_GROUP)
        for k, v in controls.items():
            if k in g:
                if not replace:
                    continue
                del g[k]
            ds = g.create_dataset(k, data=v)
            ds.attrs["unit"] = CONTROL_UNITS.get(k, "")
            ds.attrs["doc"] = CONTROL_DOCS.get(k, "")
        masks = h5.require_group(schema.MASKS_GROUP)
        for k in [k for k in masks if k.endswith(("_high", "_low")) and k.rsplit("_", 1)[0] in controls]:
            del masks[k]
        write_default_masks(h5, {k: g[k] for k in sorted(g)})
    return sorted(controls)


def save_mask(path: str | os.PathLike, name: str, expr: str, *, replace: bool = False):
    """Compile a mask expression against a database and save it under ``name`` with its definition.

    Returns the :class:`gesturedb.control.MaskResult` (frames allowed, resolved thresholds).
    """
    from gesturedb import control
    from gesturedb.db.database import Database
    from gesturedb.errors import ParameterError

    schema.check_name("mask name", name, schema.MASK_NAME_PATTERN)
    with Database(path) as db:
        if name in db.masks and not replace:
            raise ParameterError(f"mask {name!r} already exists in {db.path} "
                                 f"(definition {db.mask_definitions[name]!r}); pass replace=True to overwrite")
        # the named mask is stored as its own definition's result; other saved masks may be referenced
        others = {k: v for k, v in db.masks.items() if k != name}
        res = control.compile_mask(expr, controls=db.controls, named=others, n_frames=db.n_frames)
    if res.n_set == 0:
        raise ParameterError(f"mask {name!r} = {expr!r} allows no frame of {path}: {res.describe()}")
    with edit(path) as h5:
        g = h5.require_group(schema.MASKS_GROUP)
        if name in g:
            del g[name]
        ds = g.create_dataset(name, data=res.words)
        ds.attrs["definition"] = expr
        schema.write_json_attr(ds, "thresholds", {k: float(v) for k, v in res.thresholds.items()})
    return res


def remove_mask(path: str | os.PathLike, name: str) -> None:
    """Delete a saved mask.

    Also repairs a database damaged by an older version that accepted names
    with '/' (stored as nested groups): ``remove_mask(db, "a/b")`` or
    ``remove_mask(db, "a")`` deletes them, whatever the name.
    """
    from gesturedb.errors import ParameterError

    if not isinstance(name, str) or not name or name.strip("/.") == "":
        raise ParameterError(f"mask name: expected a mask name, got {name!r}")
    with edit(path) as h5:
        g = h5.get(schema.MASKS_GROUP)
        # the raw HDF5 group, not Database.masks: a damaged entry must still be removable
        if g is None or name not in g:
            names = sorted(g) if g is not None else []
            raise ParameterError(f"mask {name!r}: no such mask in {path}; masks: {', '.join(names) or 'none'}")
        del g[name]
        parent = name.rsplit("/", 1)[0] if "/" in name.strip("/") else None
        while parent and parent in g and len(g[parent]) == 0:  # empty groups left by a nested name
            del g[parent]
            parent = parent.rsplit("/", 1)[0] if "/" in parent else None
