"""The options of a synthesis, as one object with named defaults.

:class:`SynthOptions` holds what every synthesis method reads (seams, smoothing,
controls, keywords, which recordings to search); each method's own options
extend it: :class:`SearchOptions` for the k-NN search (:mod:`gesturedb.synth.matching`),
:class:`gesturedb.synth.graph.GraphOptions` for the motion graph. Options are frozen
dataclasses: callers pass one object along (CLI, evaluation, the live server)
instead of ten keyword arguments, and derive variants with :meth:`SynthOptions.replace`::

    opts = SearchOptions(control="left_wrist_height > p85", seed=3)
    Searcher(db).synthesize("speech.wav", options=opts)
    Searcher(db).synthesize("speech.wav", options=opts, preselect="audio")  # one field changed

Values are checked where they are used (a step needs the database's frame rate, ``k``
its number of segments), with the messages of :meth:`Searcher.synthesize`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

from gesturedb.errors import ParameterError
from gesturedb.search import STEP_FRAMES
from gesturedb.synth.repeats import DEFAULT_REPEAT_GUARD_S
from gesturedb.synth.seams import SEAM_DECAY_S

__all__ = ["PAPER_FPS", "STEP_S", "default_step", "INIT_CHOICES", "DEFAULT_INIT", "SynthOptions", "SearchOptions"]

#: The frame rate of Habibie et al.'s database, for which N = :data:`gesturedb.search.STEP_FRAMES`.
PAPER_FPS = 15.0

#: The paper's search step, N = 8 frames at its 15 fps, in seconds: a database of another frame rate steps
#: as often in time (16 frames at 30 fps). At 30 fps with 8-frame steps the seams came twice as often and the
#: seam/inside jerk was 1.18-1.23 on the four BEAT2 inputs; with 16, 1.06-1.10 (15 fps: 0.85-1.08).
STEP_S = STEP_FRAMES / PAPER_FPS


def default_step(fps: float) -> int:
    """Frames per search step at ``fps``: :data:`STEP_S` rounded, at least 1."""
    return max(1, int(round(STEP_S * float(fps))))


#: Initial-pose choices of :meth:`gesturedb.synth.Searcher.initial_pose`.
INIT_CHOICES = ("random", "mean")
#: The default initial pose: a seeded random database frame, the paper's setting
#: for all its experiments (Habibie et al. 2022, Sec. 4) and the start of every
#: path the refiner is trained on (gesturedb.refiner.data), so that a refined
#: synthesis sees the kind of path its refiner learnt from. The mean pose is an
#: average no one holds; on the held-out BEAT2 stretch its path moved the pelvis
#: at 1.41x the capture's speed against 0.92x from seed 0 and 1.02x on average
#: over seeds 0-7 (docs/evaluation.md); on the four inputs both were
#: within the capture's range.
DEFAULT_INIT = "random"

_O = TypeVar("_O", bound="SynthOptions")


@dataclass(frozen=True)
class SynthOptions:
    """What every synthesis method reads.

    Attributes
    ----------
    seam_decay_s : float
        Seconds over which the offset at a window boundary decays (0 = back-to-back
        copies as in the paper); see :mod:`gesturedb.synth.seams`.
    smooth : bool
        Savitzky-Golay smoothing of the result (GestureMaster's, window in seconds);
        off by default: it removes beat strokes.
    control : str, list or None
        A control schedule (``"0-12: left_wrist_height > p85; 12-: slow"``) or one
        mask expression for the whole synthesis; see :mod:`gesturedb.control`.
    keywords : bool or sequence of str
        Use keyword sub-databases where the transcript says their words
        (True: all of the database's, False: none, a list: only those).
    exclude : sequence of str or None
        Recordings left out of the search (their mirrored copies too).
    speaker : str, optional
        Search only this speaker's recordings of a multi-speaker database.
    """

    seam_decay_s: float = SEAM_DECAY_S
    smooth: bool = False
    control: Any = None
    keywords: Any = True
    exclude: Any = None
    speaker: str | None = None

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    def replace(self: _O, **changes) -> _O:
        """A copy with ``changes``; a name that is not an option is a :class:`ParameterError`."""
        unknown = sorted(set(changes) - set(self.field_names()))
        if unknown:
            raise ParameterError(f"{type(self).__name__}: unknown option{'s' if len(unknown) > 1 else ''} "
                                 f"{', '.join(unknown)}; expected some of {', '.join(self.field_names())}")
        return dataclasses.replace(self, **changes) if changes else self

    @classmethod
    def of(cls: type[_O], options: "SynthOptions | None" = None, **changes) -> _O:
        """``options`` as this class, with ``changes``.

        ``options`` may be None (the defaults), an instance of this class, or the options of
        another method: the fields both classes have are carried over (the shared ones, at
        least), the others take this class's defaults.
        """
        if options is None:
            base = cls()
        elif isinstance(options, cls):
            base = options
        elif isinstance(options, SynthOptions):
            mine = set(cls.field_names())
            base = cls(**{k: v for k, v in options.as_dict().items() if k in mine})
        else:
            raise ParameterError(f"options: expected a {cls.__name__} (or None), got {type(options).__name__}")
        return base.replace(**changes)

    def as_dict(self) -> dict:
        """Field name -> value (not deep-copied)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class SearchOptions(SynthOptions):
    """The k-NN search's options (:meth:`gesturedb.synth.Searcher.synthesize`): the shared ones and

    Attributes
    ----------
    k : int
        Take the k-th best candidate of each step (1 = best).
    preselect : {"pose", "audio"}
        The distance that picks one candidate per segment.
    init : {"random", "mean"}
        Initial previous pose: a database frame drawn with ``seed`` (default, as the
        paper's experiments) or the mean pose.
    seed : int or None
        Seed of ``init="random"`` (None: unseeded).
    step : int, optional
        N, frames per search step (None: :func:`default_step` at the database's rate,
        8 at 15 fps, 16 at 30 fps).
    repeat_guard_s : float
        A database window used within this many seconds of output is taken out of the
        step's allowed set (:mod:`gesturedb.synth.repeats`; 0 = off, the paper's search).
    """

    k: int = 1
    preselect: str = "pose"
    init: str = DEFAULT_INIT
    seed: int | None = 0
    step: int | None = None
    repeat_guard_s: float = DEFAULT_REPEAT_GUARD_S

    def step_at(self, fps: float) -> int:
        """The step in frames at ``fps``: :attr:`step`, or :func:`default_step` when it is None."""
        return default_step(fps) if self.step is None else self.step
