"""One search for the steps that concurrent streams are waiting on (issue 39).

Each session prepares its stream's ready step itself (:meth:`gesturedb.synth.matching.Stream.next_step`)
and hands it to the server's :class:`StepScheduler`. The scheduler's worker thread takes every step
waiting at that moment, searches them in one call (:class:`gesturedb.synth.stepbatch.StepBatch`: one
pass over the database for all of them) and gives each session its result, which the session
applies to its own stream. Steps that arrive while a batch runs wait for the next one, so a batch
holds what queued during the previous one: no timer, no step waits for others that are not there
yet. A step without candidates, or any failure of the batch call, is the affected stream's alone
(``StepBatch`` searches it by itself and returns its error).

Pose pre-selection ahead of the speech. With pre-selection ``"pose"`` (the default) a step's search
but for its audio distances reads only what is known once the step before it is applied: the
previous pose, the bitsets and the length. A session hands its stream's coming step to
:meth:`StepScheduler.ahead` right after applying a step; a second worker thread pre-selects the
coming steps of all streams in one call of the blocked kernel (:meth:`StepBatch.speculate`) while
their speech arrives (a step's 0.53 s), waiting up to ``AHEAD_GATHER_S`` for ``BLOCK_MIN`` of them
(at once when a waiting step's speech has come), and gathers each step's candidate audio windows into
one block, handing each step over as soon as its block is there. When the step's speech has come,
the server's step thread (:meth:`StepScheduler.run_step`), right after feeding the speech, checks
that the step's inputs are still those (a control or words in between make them stale) and finishes it there
(:meth:`StepScheduler.finish_ready`): the audio distances of the pre-selected candidates from their
gathered windows and the ranks (:meth:`StepBatch.finish`, about 1 ms at paper scale instead of a pass
over the database), then applies it, with no hop to another thread between. A step whose
pre-selection is still under way waits for it in :meth:`StepScheduler.search`. The result is bit for
bit the one of the usual search; a stale or missing pre-selection takes the usual way.
"""
from __future__ import annotations

import asyncio
import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from starlette.concurrency import run_in_threadpool

from gesturedb.synth.stepbatch import StepBatch

log = logging.getLogger("gesturedb.serve")

#: Most steps one batch call searches (the blocked kernel's block is 256 queries).
MAX_BATCH = 256
#: Seconds the worker thread waits without a step before it ends (the next step starts it again).
IDLE_EXIT_S = 5.0
#: Steps the pre-selection ahead waits for (up to AHEAD_GATHER_S): a blocked call costs less per step the more
#: steps it carries (617k frames, 1 thread: 11 ms a step for 3, 7 for 8, 4.8 for 16, 3-3.5 for 32 to 50),
#: though from :func:`gesturedb.search.blocked_min_queries` steps (3) it already beats a pass per step.
#: 32 and 0.25 s rather than 16 and 0.15 s (until 2026-11-28): the server's CPU per step 5 % lower, and
#: p99 lower at 16-50 real-time clients (docs/live-measurements.md, "One step thread").
BLOCK_MIN = 32
#: Seconds a coming step may wait for others before its pre-selection starts: a step's speech takes
#: 0.53 s to come, and a call of 32-50 steps 0.1-0.15 s at paper scale, so waiting lets one blocked call
#: serve many streams' coming steps and still ends before their speech.
AHEAD_GATHER_S = 0.25
#: Threads that run the sessions' step work once a step's speech has come (:meth:`StepScheduler.run_step`:
#: the feed, the finish from the pre-selection, the apply), first come, first served. One: that work is
#: Python holding the interpreter lock, so more threads do not run it at once but share the lock in
#: 5 ms turns, and the steps of streams whose speech comes together (a burst) all end near the end of
#: the burst instead of one after the other (docs/live-measurements.md, "One step thread").
STEP_THREADS = 1


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

    def __init__(self, searcher, *, max_batch: int = MAX_BATCH, threads: int = 1, ahead: bool = True,
                 step_threads: int = STEP_THREADS):
        self.batch = StepBatch(searcher, threads=threads)
        self.step_threads = int(step_threads)
        self._step_pool: ThreadPoolExecutor | None = None  # made at the first step (after a fork: its own)
        self.max_batch = max_batch
        self._waiting: list[tuple] = []  # (step, future, its event loop)
        lock = threading.RLock()
        self._cond = threading.Condition(lock)
        # the pre-selecting thread's own condition on the same lock: a step never wakes it, nor a
        # coming step the search's worker
        self._ahead_cond = threading.Condition(lock)
        self._worker: threading.Thread | None = None
        self.n_steps = self.n_calls = 0
        self.busy_s = 0.0
        #: whether coming steps are pre-selected ahead of their speech (see the module's docstring)
        self.ahead_enabled = ahead
        self._ahead: dict = {}  # stream -> _Ahead, its coming step
        self._ahead_queue: list[_Ahead] = []
        self._ahead_now = False  # a queued step's speech has come: start the next call without waiting
        self._ahead_worker: threading.Thread | None = None
        #: steps finished from their pre-selection, pre-selections found stale, calls, seconds in them
        self.n_ahead_used = self.n_ahead_stale = self.n_ahead_calls = 0
        self.ahead_busy_s = 0.0

    def stats(self) -> dict:
        """``{"steps", "calls", "busy_s", "alone", "ahead"}``: steps searched, batch calls, seconds in them,
        steps a batch left to their own stream (the repeat guard left them no candidate), and of the
        pre-selection ahead of the speech: steps finished from it, pre-selections found stale (a control
        change, say), its calls and seconds."""
        return {"steps": self.n_steps, "calls": self.n_calls, "busy_s": round(self.busy_s, 6),
                "alone": self.batch.n_alone,
                "ahead": {"used": self.n_ahead_used, "stale": self.n_ahead_stale, "calls": self.n_ahead_calls,
                          "busy_s": round(self.ahead_busy_s, 6)}}

    async def run_step(self, call, *args):
        """``call(*args)`` in the scheduler's step thread (:data:`STEP_THREADS`), after the calls submitted
        before it; returns its result or raises its exception. The sessions' per-step work goes here instead
        of to the event loop's thread pool, where every session's step ran in a thread of its own."""
        with self._cond:
            if self._step_pool is None:
                self._step_pool = ThreadPoolExecutor(self.step_threads, thread_name_prefix="gesturedb-step")
        return await asyncio.wrap_future(self._step_pool.submit(call, *args))

    # -- the coming steps, pre-selected while their speech arrives -------------------------------
    def ahead(self, up) -> None:
        """Pre-select step ``up`` (a stream's :meth:`~gesturedb.synth.matching.Stream.upcoming_step`, or None:
        nothing) in the background, replacing what was queued for its stream. Call it from the event loop
        of the session that will :meth:`search` the step."""
        if up is None or not self.ahead_enabled:
            return
        entry = _Ahead(up, asyncio.get_running_loop())
        with self._cond:
            old = self._ahead.get(up.stream)
            if old is not None and old.state == _QUEUED:
                self._ahead_queue.remove(old)
            self._ahead[up.stream] = entry
            self._ahead_queue.append(entry)
            if self._ahead_worker is None:
                self._ahead_worker = threading.Thread(target=self._run_ahead, name="gesturedb-step-ahead",
                                                      daemon=True)
                self._ahead_worker.start()
            self._ahead_cond.notify()

    def forget(self, stream) -> None:
        """Drop what is kept for ``stream`` (its session ended)."""
        with self._cond:
            old = self._ahead.pop(stream, None)
            if old is not None and old.state == _QUEUED:
                self._ahead_queue.remove(old)

    async def _take_ahead(self, sq):
        """The pre-selected table of step ``sq`` when one is there (waiting for it if it is being computed)
        and still fits the step; else None (and the step is searched as usual)."""
        with self._cond:
            entry = self._ahead.pop(sq.stream, None)
            if entry is None:
                return None
            if entry.state == _QUEUED:  # its speech came first: pre-select now, without gathering more
                self._ahead_now = True
                self._ahead_cond.notify()
        if entry.state != _DONE:
            await entry.fut
        return self._fitting_table(entry, sq)

    def _fitting_table(self, entry, sq):
        """The done pre-selection ``entry``'s table when it fits step ``sq`` (its inputs but the audio are the
        same); else None (a stale one counted), and the step is searched as usual."""
        if entry.table is None:
            return None
        if not entry.sq.same_but_audio(sq):
            self.n_ahead_stale += 1
            return None
        return entry.table

    def _finish(self, sq, table):
        """:meth:`StepBatch.finish` of step ``sq`` from its pre-selected ``table``, counted when it could."""
        got = self.batch.finish(sq, table)
        if got is not None:
            self.n_ahead_used += 1
        return got

    def _run_ahead(self) -> None:
        while True:
            with self._cond:
                if not self._ahead_queue:
                    self._ahead_cond.wait(IDLE_EXIT_S)
                if not self._ahead_queue:
                    self._ahead_worker = None
                    return
                # fewer steps than a blocked call wants: wait a little for more (off every step's path:
                # the speech of the oldest is still coming), then take what is there
                while 0 < len(self._ahead_queue) < BLOCK_MIN and not self._ahead_now:
                    left = self._ahead_queue[0].t + AHEAD_GATHER_S - time.monotonic()
                    if left <= 0:
                        break
                    self._ahead_cond.wait(left)
                self._ahead_now = False
                todo, self._ahead_queue = self._ahead_queue[:self.max_batch], self._ahead_queue[self.max_batch:]
                for e in todo:
                    e.state = _RUNNING
            t = time.perf_counter()
            try:
                # each step's table goes to its session as soon as its windows are gathered, not after
                # the whole call's: the oldest steps' speech may already be there
                got = self.batch.speculate([e.sq for e in todo],
                                           ready=lambda j, table, todo=todo: _done(todo[j], table))
            except Exception:  # a bug: those steps are searched as usual
                log.exception("pre-selection ahead of the speech failed")
                got = [None] * len(todo)
            self.ahead_busy_s += time.perf_counter() - t
            self.n_ahead_calls += 1
            for e, table in zip(todo, got):
                if e.state != _DONE:
                    _done(e, table)

    # -- the steps whose speech has come -----------------------------------------------------
    def finish_ready(self, sq):
        """``(res, relaxed)`` of step ``sq`` finished from its pre-selection when that is done and still fits,
        computed in the calling thread (the step thread, between a session's feed and its apply: no hop to
        another thread); else None, and :meth:`search` takes the step (waiting for a pre-selection under way,
        or searching it with the other waiting steps)."""
        if not self.ahead_enabled:
            return None
        with self._cond:
            entry = self._ahead.get(sq.stream)
            if entry is None or entry.state != _DONE:
                return None
            del self._ahead[sq.stream]
        table = self._fitting_table(entry, sq)
        return None if table is None else self._finish(sq, table)

    async def search(self, sq):
        """``(res, relaxed)`` of step ``sq`` (as its stream's ``search_step`` returns them): finished from its
        pre-selection when :meth:`ahead` made one that still fits, else searched with the other steps
        waiting; raises the step's own GestureDBError when it has no candidate."""
        table = await self._take_ahead(sq) if self.ahead_enabled else None
        if table is not None:
            got = await run_in_threadpool(self._finish, sq, table)
            if got is not None:
                return got
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


_QUEUED, _RUNNING, _DONE = range(3)


class _Ahead:
    """A stream's coming step, pre-selected (or to be) ahead of its speech."""

    __slots__ = ("sq", "loop", "fut", "state", "table", "t")

    def __init__(self, sq, loop):
        self.sq, self.loop = sq, loop
        self.t = time.monotonic()  # when it was queued
        self.fut = loop.create_future()  # resolved when the worker is done with it
        self.state = _QUEUED
        self.table = None  # (starts, pose_dist, windows) once done; None when it cannot be finished so


def _done(e: _Ahead, table) -> None:
    """Hand pre-selected step ``e`` its table (None: it is searched as usual) and wake its session."""
    e.table, e.state = table, _DONE
    try:
        e.loop.call_soon_threadsafe(_resolve, e.fut, None)
    except RuntimeError:
        pass  # that session's event loop is closed


def _resolve(fut: asyncio.Future, r) -> None:
    if fut.done():  # the session was cancelled (its client left)
        return
    if isinstance(r, BaseException):
        fut.set_exception(r)
    else:
        fut.set_result(r)
