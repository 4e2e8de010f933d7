"""One search for the steps that concurrent streams are waiting on (issue 39).

Each session prepares its stream's ready step itself (:meth:`gesturedb.synth.matching.Stream.next_step`)
and hands it to the server's :class:`StepScheduler`. The scheduler's worker thread takes every step
waiting at that moment, searches them in one call (:class:`gesturedb.synth.stepbatch.StepBatch`: one
pass over the database for all of them) and gives each session its result, which the session
applies to its own stream. Steps that arrive while a batch runs wait for the next one, so a batch
holds what queued during the previous one: no timer, no step waits for others that are not there
yet. A step without candidates, or any failure of the batch call, is the affected stream's alone
(``StepBatch`` searches it by itself and returns its error).
"""
from __future__ import annotations

import asyncio
import logging
import threading
import time

from gesturedb.synth.stepbatch import StepBatch

log = logging.getLogger("gesturedb.serve")

#: Most steps one batch call searches (the blocked kernel's block is 256 queries).
MAX_BATCH = 256
#: Seconds the worker thread waits without a step before it ends (the next step starts it again).
IDLE_EXIT_S = 5.0


class StepScheduler:
    """Gather the streams' waiting steps and search them in one call in a worker thread.

    Parameters
    ----------
    searcher : gesturedb.synth.Searcher
        The searcher every stream of the server shares.
    max_batch : int
        Most steps per call; more waiting steps make several calls in a row.
    threads : int
        Threads of the batched search (1: the search takes one core while the sessions' Python,
        their features, assembly and messages, takes the others; measured faster on 2 cores than
        a search on both).

    Attributes
    ----------
    n_steps, n_calls : int
        Steps searched and batch calls made so far (``n_steps / n_calls`` is the mean batch).
    busy_s : float
        Seconds the worker spent in batch calls.
    """

    def __init__(self, searcher, *, max_batch: int = MAX_BATCH, threads: int = 1):
        self.batch = StepBatch(searcher, threads=threads)
        self.max_batch = max_batch
        self._waiting: list[tuple] = []  # (step, future, its event loop)
        self._cond = threading.Condition()
        self._worker: threading.Thread | None = None
        self.n_steps = self.n_calls = 0
        self.busy_s = 0.0

    def stats(self) -> dict:
        """``{"steps", "calls", "busy_s", "alone"}``: steps searched, batch calls, seconds in them, and steps
        a batch left to their own stream (the repeat guard left them no candidate)."""
        return {"steps": self.n_steps, "calls": self.n_calls, "busy_s": round(self.busy_s, 6),
                "alone": self.batch.n_alone}

    async def search(self, sq):
        """``(res, relaxed)`` of step ``sq`` (as its stream's ``search_step`` returns them), searched with
        the other steps waiting; raises the step's own GestureDBError when it has no candidate."""
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        with self._cond:
            self._waiting.append((sq, fut, loop))
            if self._worker is None:
                self._worker = threading.Thread(target=self._run, name="gesturedb-step-batch", daemon=True)
                self._worker.start()
            self._cond.notify()
        return await fut

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._waiting:
                    self._cond.wait(IDLE_EXIT_S)
                if not self._waiting:
                    self._worker = None  # a later step starts a new worker (under the same lock)
                    return
                todo, self._waiting = self._waiting[:self.max_batch], self._waiting[self.max_batch:]
            t = time.perf_counter()
            try:
                got = self.batch.search([sq for sq, _, _ in todo])
            except Exception as exc:  # a bug, not a step without candidates: every waiting stream hears of it
                log.exception("batched search failed")
                got = [exc] * len(todo)
            self.busy_s += time.perf_counter() - t
            self.n_calls += 1
            self.n_steps += len(todo)
            for (_, fut, loop), r in zip(todo, got):
                try:
                    loop.call_soon_threadsafe(_resolve, fut, r)
                except RuntimeError:
                    pass  # that session's event loop is closed: nobody waits for this result


def _resolve(fut: asyncio.Future, r) -> None:
    if fut.done():  # the session was cancelled (its client left)
        return
    if isinstance(r, BaseException):
        fut.set_exception(r)
    else:
        fut.set_result(r)
