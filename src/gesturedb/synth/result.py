"""What a synthesis returns: the motion and where every part of it came from (provenance)."""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

from gesturedb.errors import InputFileError
from gesturedb.io.atomic import write_text
from gesturedb.motion import Motion


@dataclass
class SynthResult:
    """A synthesized motion and where every part of it came from.

    Attributes
    ----------
    motion : gesturedb.motion.Motion
        At the database fps, exactly ``n_frames`` long (the length of the speech).
    source_frames : ndarray [shape=(T,)], int64
        Database frame copied to each output frame (before blending).
    boundaries : ndarray, int64
        Output frames where a new window starts (t = step, 2 step, ...).
    steps : list of dict
        Provenance, one entry per search step (see :meth:`Searcher.synthesize`).
    """

    motion: object
    source_frames: np.ndarray
    boundaries: np.ndarray
    steps: list
    fps: float
    audio_path: str | None = None
    options: dict = field(default_factory=dict)
    #: how often database windows are played again (:func:`gesturedb.synth.repeats.repeat_stats`), or None
    repeats: dict | None = None

    @property
    def n_frames(self) -> int:
        return int(self.source_frames.shape[0])

    @property
    def positions(self) -> np.ndarray:
        """ndarray [shape=(T, J, 3)], world metres."""
        return self.motion.positions

    def provenance(self) -> dict:
        return {
            "audio": self.audio_path,
            "fps": self.fps,
            "n_frames": self.n_frames,
            "duration_s": self.n_frames / self.fps,
            "options": self.options,
            **({"repeats": self.repeats} if self.repeats is not None else {}),
            "steps": self.steps,
        }

    def write_provenance(self, path: str | os.PathLike) -> None:
        """Write the provenance as strict JSON (a NaN or inf distance is an error, never ``NaN`` in the file)."""

        try:
            text = json.dumps(self.provenance(), indent=1, allow_nan=False)
        except ValueError as exc:
            raise InputFileError(path, f"provenance: expected finite numbers ({exc}); the database's features "
                                       "are not finite") from None
        write_text(path, text)


@dataclass
class StreamChunk:
    """What one :meth:`gesturedb.synth.stream.Stream.push` (or ``finish``) made final: the frames of a live synthesis.

    Attributes
    ----------
    start : int
        Output frame index of the chunk's first frame.
    motion : gesturedb.motion.Motion
        The new final frames at the database fps (``motion.n_frames`` may be 0).
    steps : list of dict
        Provenance of the search steps whose frames all became final, keys as
        :attr:`gesturedb.synth.result.SynthResult.steps` of the k-NN.
    """

    start: int
    motion: Motion
    steps: list = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return int(self.motion.rotations.shape[0])


def chunk_motion(skeleton, fps, rot, root) -> Motion:
    """A chunk's :class:`Motion` of ``rot`` (F, J, 4) and ``root`` (F, 3), F >= 0."""
    if rot.shape[0]:
        return Motion(skeleton=skeleton, fps=fps, rotations=rot, root_positions=root)
    # Motion checks F >= 1 for what users build; a chunk may have no frame yet
    m = object.__new__(Motion)
    m.skeleton, m.fps, m.rotations, m.root_positions = skeleton, float(fps), rot, root
    return m
