"""Edits of an existing database: saved masks and control features.

Every edit goes through :func:`gesturedb.db.storage.edit` (compact copy, edit,
rename), and reads what it decides from while holding the database's write lock
(:func:`gesturedb.db.storage.locked`): two concurrent ``masks add`` of one name
act as if run one after the other, so the second is refused. Many masks go in
one edit (:func:`save_masks`, ``gesturedb masks DB add N1 E1 N2 E2`` or ``--from FILE``).
"""
from __future__ import annotations

import os
import re

from gesturedb import control
from gesturedb.db import schema, store
from gesturedb.db.build import save_mask_bits, write_default_masks
from gesturedb.db.database import Database
from gesturedb.db.storage import edit, locked
from gesturedb.errors import InputFileError, ParameterError, echo
from gesturedb.features.controls import CONTROL_DOCS, CONTROL_UNITS, control_features
from gesturedb.io.joints import BODY_ROLES, FEATURE_ROLES, find_joints
from gesturedb.io.text import read_text_lines


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

    with locked(path):
        with Database(path) as db:
            names = db.joint_names
            joints = find_joints(names, FEATURE_ROLES + BODY_ROLES,
                                 mapping={r: n for r, n in db.feature_joints.items()}, source=db.path)
            parts = [control_features(np.asarray(db.joint_positions[r.start_frame:r.stop_frame], dtype=np.float64),
                                      joints=joints, fps=db.fps) for r in db.recordings]
        controls = {k: np.concatenate([p[k] for p in parts]).astype(np.float32) for k in sorted(parts[0])}
        _write_controls(path, controls, replace)
    return sorted(controls)


def _write_controls(path, controls: dict, replace: bool) -> None:
    C, M = schema.CONTROLS_GROUP, schema.MASKS_GROUP
    with edit(path) as h5:
        store.ensure_group(h5, C)
        for k, v in controls.items():
            if store.exists(h5, f"{C}/{k}"):
                if not replace:
                    continue
                store.delete(h5, f"{C}/{k}")
            store.create(h5, f"{C}/{k}", v, attrs={"unit": CONTROL_UNITS.get(k, ""), "doc": CONTROL_DOCS.get(k, "")})
        store.ensure_group(h5, M)
        for k in store.members(h5, M):
            if k.endswith(("_high", "_low")) and k.rsplit("_", 1)[0] in controls:
                store.delete(h5, f"{M}/{k}")
        write_default_masks(h5, {k: store.array(h5, f"{C}/{k}") for k in store.members(h5, C)})


def save_mask(path: str | os.PathLike, name: str, expr: str, *, replace: bool = False):
    """Compile a mask expression against a database and save it under ``name`` with its definition.

    Returns the :class:`gesturedb.control.MaskResult` (frames allowed, resolved thresholds).
    """
    return save_masks(path, [(name, expr)], replace=replace)[name]


def _mask_items(masks) -> list[tuple[str, str]]:
    items = list(masks.items()) if isinstance(masks, dict) else list(masks)
    if not items:
        raise ParameterError("masks: expected at least one (name, expression), got none")
    seen = set()
    for item in items:
        if not (isinstance(item, tuple) and len(item) == 2 and isinstance(item[1], str)):
            raise ParameterError(f"masks: expected (name, expression) pairs of strings, got {echo(item)}")
        schema.check_name("mask name", item[0], schema.MASK_NAME_PATTERN)
        if item[0] in seen:
            raise ParameterError(f"mask {item[0]!r}: given twice in one edit; expected each name once")
        seen.add(item[0])
    return items


def save_masks(path: str | os.PathLike, masks, *, replace: bool = False) -> dict:
    """Compile several mask expressions and save them in one atomic edit (one copy of the file).

    Parameters
    ----------
    path : str or os.PathLike
    masks : dict of str to str, or list of (name, expression)
        In order: an expression may name the masks saved before it in the same call.
    replace : bool
        Overwrite saved masks of the same names.

    Returns
    -------
    dict of str to gesturedb.control.MaskResult

    Raises
    ------
    ParameterError
        A bad name or expression, a name already saved (without ``replace``), or a
        mask that allows no frame: the whole edit is refused and the file unchanged.
    """

    items = _mask_items(masks)
    results = {}
    with locked(path):  # the names taken are read under the lock: a concurrent add of one name is refused
        with Database(path) as db:
            saved = db.masks
            for name, _expr in items:
                if name in saved and not replace:
                    raise ParameterError(f"mask {name!r} already exists in {db.path} "
                                         f"(definition {db.mask_definitions[name]!r}); pass replace=True to "
                                         "overwrite")
            new_names = {name for name, _ in items}
            for name, expr in items:
                # a mask is stored as its own definition's result; the other saved masks and those of
                # this call defined before it may be referenced
                others = {k: v for k, v in saved.items() if k not in new_names}
                others.update({k: r.words for k, r in results.items()})
                res = control.compile_mask(expr, controls=db.controls, named=others, n_frames=db.n_frames)
                if res.n_set == 0:
                    raise ParameterError(f"mask {name!r} = {expr!r} allows no frame of {path}: {res.describe()}")
                results[name] = res
        with edit(path) as h5:
            store.ensure_group(h5, schema.MASKS_GROUP)
            for name, res in results.items():
                save_mask_bits(h5, name, res, dict(items)[name])
    return results


_MASK_LINE = re.compile(r"\s*([^\s=#]+)\s*=\s*(.*?)\s*")


def read_mask_file(path) -> list[tuple[str, str]]:
    """Masks from a text file, one ``NAME = EXPRESSION`` per line; blank lines and ``#`` comments skipped.

    Raises
    ------
    InputFileError
        The file cannot be read, or a line is not ``NAME = EXPRESSION`` with a valid
        name (the message names the line).
    """

    lines = read_text_lines(path)
    items = []
    for k, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0]
        if not text.strip():
            continue
        m = _MASK_LINE.fullmatch(text)
        if m is None or not m.group(2):
            raise InputFileError(path, f"line {k}: expected NAME = EXPRESSION, got {text.strip()[:60]!r}")
        try:
            schema.check_name("mask name", m.group(1), schema.MASK_NAME_PATTERN)
        except ParameterError as exc:
            raise InputFileError(path, f"line {k}: {exc}") from None
        items.append((m.group(1), m.group(2)))
    if not items:
        raise InputFileError(path, "expected lines NAME = EXPRESSION, got none")
    return items


def remove_mask(path: str | os.PathLike, name: str) -> None:
    """Delete a saved mask.

    Also repairs a database damaged by an older version that accepted names
    with '/' (stored as nested groups): ``remove_mask(db, "a/b")`` or
    ``remove_mask(db, "a")`` deletes them, whatever the name.
    """

    if not isinstance(name, str) or not name or name.strip("/.") == "":
        raise ParameterError(f"mask name: expected a mask name, got {name!r}")
    M = schema.MASKS_GROUP
    with edit(path) as h5:
        # the stored objects, not Database.masks: a damaged entry (a group) must still be removable
        if not store.exists(h5, M) or not store.exists(h5, f"{M}/{name}"):
            names = store.members(h5, M)
            raise ParameterError(f"mask {name!r}: no such mask in {path}; masks: {', '.join(names) or 'none'}")
        store.delete(h5, f"{M}/{name}")
        parent = name.rsplit("/", 1)[0] if "/" in name.strip("/") else None
        while parent and store.exists(h5, f"{M}/{parent}") and not store.members(h5, f"{M}/{parent}"):
            store.delete(h5, f"{M}/{parent}")  # empty groups left by a nested name
            parent = parent.rsplit("/", 1)[0] if "/" in parent else None
