"""Derived data computed once in a background thread while the work that does not need it goes on.

A stream's first frame should not wait for what a database's first search builds from it (the pose
projection filter, the seams' typical accelerations: seconds at paper scale); :class:`Background`
computes such a value in a daemon thread, and :class:`Awaited` hands a tuple of it to code that
indexes it, waiting only there. Used by :class:`gesturedb.synth.matching.Searcher`.
"""
from __future__ import annotations

import threading

__all__ = ["Background", "Awaited"]


class Background:
    """A value computed once in a daemon thread: :meth:`ready` asks, :meth:`result` waits (and
    raises what the computation raised). Daemon, so that a process that never needed the value
    does not wait for it at exit; what it reads (memory-mapped arrays) outlives the database's
    close (:meth:`gesturedb.db.database.Database._mapped`)."""

    def __init__(self, fn, name: str):
        self._fn, self._value, self._exc = fn, None, None
        self._done = threading.Event()
        threading.Thread(target=self._run, name=name, daemon=True).start()

    def _run(self) -> None:
        try:
            self._value = self._fn()
        except BaseException as exc:  # noqa: BLE001 - handed to whoever waits for the value
            self._exc = exc
        finally:
            self._done.set()

    def ready(self) -> bool:
        return self._done.is_set()

    def wait(self) -> None:
        """Until the computation has ended (a value or an exception)."""
        self._done.wait()

    def result(self):
        self._done.wait()
        if self._exc is not None:
            raise self._exc
        return self._value


class Awaited:
    """A tuple computed by a :class:`Background`, waited for at its first indexing (``x[0]``)."""

    def __init__(self, job: Background):
        self._job = job

    def __getitem__(self, i):
        return self._job.result()[i]

    def __len__(self) -> int:
        return len(self._job.result())

    def __iter__(self):
        return iter(self._job.result())
