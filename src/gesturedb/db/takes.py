"""Recordings as they come from capture pipelines: the files of one take, who speaks, mirroring.

:class:`RecordingSource` names the files of one recording (paired by stem, or
listed in a pairing file, :func:`read_pairing_file`); :func:`infer_speaker`
reads the speaker only from naming schemes we know; :func:`mirrored_copy`
mirrors a take on its own captured (never quite symmetric) skeleton. Used by
:mod:`gesturedb.db.build`, which re-exports these names.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gesturedb.errors import InputFileError, ParameterError
from gesturedb.motion import Motion

__all__ = ["MIRROR_NOTE_REL", "PAIRING_COLUMNS", "RecordingSource", "infer_speaker", "mirrored_copy",
           "read_pairing_file"]


@dataclass(frozen=True)
class RecordingSource:
    """The files of one recording, paired by stem.

    ``span_s`` optionally keeps only ``[start, end)`` seconds of the recording
    (motion, audio and words alike), e.g. to hold a stretch out for evaluation;
    word times are then relative to ``start``. ``speaker`` names the speaker
    (None: ``BuildConfig.speaker``, else :func:`infer_speaker`).
    """

    name: str
    motion: str
    audio: str
    transcript: str | None
    span_s: tuple[float, float] | None = None
    speaker: str | None = None


# BEAT / BEAT2 file names: <speaker id>_<name>_<take type>_<start>_<end>, e.g. 2_scott_0_1_1
_BEAT_STEM = re.compile(r"^\d+_([A-Za-z]+)_\d+_\d+_\d+$")


def infer_speaker(source: RecordingSource) -> str:
    """The speaker of a recording: its own ``speaker``, else from a naming scheme we know, else the folder.

    Only BEAT's ``<id>_<name>_<type>_<start>_<end>`` stems name the speaker
    (``2_scott_0_1_1`` -> ``scott``); any other stem (``067_Speech_2_x_1_0``)
    says nothing about who speaks, so the motion file's folder name is used.
    """
    if source.speaker:
        return source.speaker
    m = _BEAT_STEM.match(source.name)
    if m:
        return m.group(1).lower()
    return Path(source.motion).resolve().parent.name


PAIRING_COLUMNS = ("motion", "audio", "transcript", "speaker", "name")


def read_pairing_file(path) -> list[RecordingSource]:
    """Recordings listed in a CSV pairing file.

    The first line names the columns: ``motion`` and ``audio`` (required),
    ``transcript``, ``speaker`` and ``name`` (optional; the name defaults to the
    motion file's stem). Relative paths are relative to the pairing file's folder;
    an empty transcript cell means none.

    Raises
    ------
    InputFileError
        Unreadable file, missing or unknown columns, a row without motion or
        audio, a listed file that does not exist; the message names the line.
    """
    import csv

    path = Path(path)
    try:
        # utf-8-sig: Excel's "CSV UTF-8" (and some exporters) start the file with a BOM
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputFileError(path, f"cannot read the pairing file: {exc}") from None
    rows = [(i + 1, r) for i, r in enumerate(rows) if any(c.strip() for c in r)]
    if not rows:
        raise InputFileError(path, "pairing file: expected a header line (motion,audio[,transcript,speaker,name]), "
                                   "got an empty file")
    header = [c.strip().lower() for c in rows[0][1]]
    unknown = [c for c in header if c not in PAIRING_COLUMNS]
    missing = [c for c in ("motion", "audio") if c not in header]
    if unknown or missing or len(set(header)) != len(header):
        raise InputFileError(path, f"line {rows[0][0]}: header: expected the columns motion, audio and optionally "
                                   f"transcript, speaker, name (each once); got {','.join(header)}")
    out = []
    for ln, row in rows[1:]:
        if len(row) != len(header):
            raise InputFileError(path, f"line {ln}: expected {len(header)} values (as the header), got {len(row)}")
        cell = {k: v.strip() for k, v in zip(header, row)}
        for k in ("motion", "audio", "transcript"):
            if cell.get(k):
                p = Path(cell[k])
                p = p if p.is_absolute() else path.parent / p
                if not p.is_file():
                    raise InputFileError(path, f"line {ln}: {k}: no such file {str(p)!r}")
                cell[k] = str(p)
            elif k != "transcript":
                raise InputFileError(path, f"line {ln}: {k}: expected a file, got an empty cell")
        out.append(RecordingSource(cell.get("name") or Path(cell["motion"]).stem, cell["motion"], cell["audio"],
                                   cell.get("transcript") or None, speaker=cell.get("speaker") or None))
    if not out:
        raise InputFileError(path, "pairing file: expected at least one recording after the header, got none")
    return out


#: left/right bone-length differences up to this fraction pass without a note in the build report
MIRROR_NOTE_REL = 0.01


def mirrored_copy(motion, path) -> tuple:
    """The left/right mirrored performance on the captured skeleton, and a note for the build report.

    Every captured actor's skeleton differs a little between its sides, so the
    mirrored copy **keeps the skeleton and swaps the rotations**
    (:meth:`gesturedb.motion.Motion.mirror`, then the original bones): the
    mirrored performer's left arm moves as the original right arm did,
    reflected, with the left arm's bone lengths. One skeleton then serves the
    whole database. A symmetric skeleton gives exactly the reflected positions;
    one whose sides differ by a few percent gives positions off by about that
    fraction of a limb (tested).

    Parameters
    ----------
    motion : Motion
    path : str
        The motion file, for messages.

    Returns
    -------
    mirrored : Motion
        Same skeleton as ``motion``.
    note : str or None
        Says how much the sides differ, when more than 1 %.

    Raises
    ------
    InputFileError
        If the skeleton has no left/right joint pairs (names such as
        ``LeftArm``/``RightArm``, ``l_wrist``/``r_wrist``), or swapping them does
        not map the hierarchy onto itself.
    """

    sk = motion.skeleton
    perm = sk.mirror_permutation()
    if np.array_equal(perm, np.arange(sk.n_joints)):
        raise InputFileError(path, f"mirror: expected left/right joint pairs (e.g. LeftArm/RightArm, l_wrist/r_wrist), "
                                   f"got none among the {sk.n_joints} joints ({', '.join(sk.names[:8])}"
                                   f"{', ...' if sk.n_joints > 8 else ''}); build without --mirror")
    try:
        flipped = motion.mirror()
    except ParameterError as exc:
        raise InputFileError(path, f"mirror: {exc}") from None
    mirrored = Motion(skeleton=sk, fps=motion.fps, rotations=flipped.rotations, root_positions=flipped.root_positions)
    bone = np.linalg.norm(sk.offsets, axis=1)
    bone[0] = 0.0  # the root's offset is where it rests, no bone
    diff = np.abs(bone - bone[perm]) / np.maximum(np.maximum(bone, bone[perm]), 1e-6 * sk.scale())
    diff[bone + bone[perm] < 1e-3 * sk.scale()] = 0.0  # zero-length helpers
    j = int(np.argmax(diff))
    note = None
    if diff[j] > MIRROR_NOTE_REL:
        note = (f"left/right bones differ by up to {diff[j]:.1%} ({sk.names[j]} {bone[j]:.3f} m vs "
                f"{sk.names[perm[j]]} {bone[perm[j]]:.3f} m); the mirrored copy keeps the captured skeleton "
                "and swaps the rotations")
    return mirrored, note
