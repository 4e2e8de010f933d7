"""One prepared search step of a live stream (:class:`StepQuery`), what its search reads.

Kept apart from :mod:`gesturedb.synth.matching` (the stream that makes them) so that the
searches that take them (:mod:`gesturedb.synth.stepbatch`, the server's scheduler) read it on
its own.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["StepQuery"]


@dataclass(eq=False)
class StepQuery:
    """One search step of a :class:`Stream`, prepared (:meth:`Stream.next_step`): what its search reads.

    The search itself is either the stream's own (:meth:`Stream.search_step`) or one call for
    the steps of many streams (:class:`gesturedb.synth.stepbatch.StepBatch`); both give the
    same result, and :meth:`Stream.complete_step` applies it.

    Attributes
    ----------
    stream : Stream
        The stream whose step this is.
    i, t, n : int
        Step index, its first output frame and its length (frames).
    query : ndarray [shape=(n, Da)], float32
        The step's standardised audio features.
    prev : ndarray [shape=(Dp,)], float32
        Pose feature of the last output frame (or the initial pose).
    row : ndarray [shape=(ceil(F/64),)], uint64, or None
        The step's control and keyword bitset; None when unconstrained.
    allowed : ndarray [shape=(ceil(F/64),)], uint64
        ``row``, or every frame when None (what the search without the guard takes).
    recent : list of (int, int)
        Database frame ranges ``[a, b)`` of the windows within the repeat guard.
    guarded : ndarray [shape=(ceil(F/64),)], uint64, or None
        ``allowed`` with the ``recent`` frames cleared (tried first); None when ``recent`` is empty.
    label : tuple (control, keyword) or None
    kw_row : ndarray or None
        The keyword sub-database's bitset (for the message of a step without candidates).
    """

    stream: object  # the Stream (not imported: matching imports this module)
    i: int
    t: int
    n: int
    query: np.ndarray
    prev: np.ndarray
    row: np.ndarray | None
    allowed: np.ndarray
    recent: list
    guarded: np.ndarray | None
    label: tuple | None
    kw_row: np.ndarray | None

    def same_but_audio(self, other: StepQuery) -> bool:
        """Whether ``other`` is this step with the same search inputs but for its audio: the same stream,
        step and length, previous pose, bitset and repeat guard (a step prepared ahead of its speech by
        :meth:`Stream.upcoming_step`, checked against the step once its speech came)."""
        def same(a, b):
            return a is b or (a is not None and b is not None and np.array_equal(a, b))

        return (self.stream is other.stream and self.i == other.i and self.n == other.n
                and same(self.prev, other.prev) and same(self.allowed, other.allowed)
                and self.recent == other.recent)
