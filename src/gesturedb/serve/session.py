"""One WebSocket stream: audio and control messages in, frames and provenance out.

A session owns its synthesizer and nothing else: whatever a client sends ends, at
worst, its own stream with an error message and a close code; the other streams and
the shared database never see it. Every blocking call into the synthesizer runs in
a worker thread so that the event loop keeps serving the others (a step's feed, finish and apply in
the step scheduler's one step thread, in the order the steps' speech came:
:meth:`gesturedb.serve.batcher.StepScheduler.run_step`).

An audio message costs the event loop as little as it can (13 of them make a step at
40 ms each): its size is checked and its bytes kept; they are decoded and fed to the
stream in one piece once a step can be ready. The idle limit is one timer per session,
not a timeout entered per message (``_IdleTimer``).
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
import time

import anyio
import numpy as np
from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocket, WebSocketDisconnect, WebSocketState

from gesturedb.errors import GestureDBError, ParameterError, echo
from gesturedb.motion import Motion
from gesturedb.serve import protocol as P

log = logging.getLogger("gesturedb.serve")

#: Most words one ``words`` message may carry, and the longest word.
MAX_WORDS_PER_MESSAGE = 10000
MAX_WORD_CHARS = 100


class _Close(Exception):
    """End this session: send an error message (when ``code_name``), then close with ``close_code``."""

    def __init__(self, close_code: int, code_name: str | None = None, message: str = ""):
        super().__init__(message)
        self.close_code, self.code_name, self.message = close_code, code_name, message


class _IdleTimer:
    """The idle limit of a session: its wait for a client message is cancelled once it has lasted ``idle_s``.

    A timeout entered per message (``anyio.fail_after``: a cancel scope, a timer made and cancelled) was 4 %
    of a loaded server's time (docs/live-measurements.md, "The event loop's per-message work"). Here a wait
    costs a clock read, and one timer per session wakes at most once per ``idle_s`` while messages come: when
    it finds the current wait younger than the limit, it sleeps again until that wait's deadline. Made in the
    session's task (asyncio: uvicorn, Starlette's TestClient), whose wait it cancels.
    """

    def __init__(self, idle_s: float):
        self.idle_s = idle_s
        self.loop = asyncio.get_running_loop()
        self.task = asyncio.current_task()
        #: when the session began waiting for the message it waits for (loop time), None when not waiting
        self.wait_since: float | None = None
        self._fired = False
        self._handle = self.loop.call_at(self.loop.time() + idle_s, self._check)

    def waiting(self) -> None:
        """The session waits for a message from now (``wait_since = None`` when one came)."""
        self.wait_since = self.loop.time()

    def _check(self) -> None:
        now = self.loop.time()
        if self.wait_since is None:  # busy with a message: a wait begun now ends idle_s from now at the earliest
            self._handle = self.loop.call_at(now + self.idle_s, self._check)
        elif now < self.wait_since + self.idle_s:
            self._handle = self.loop.call_at(self.wait_since + self.idle_s, self._check)
        else:  # the session's task is suspended in that wait (this runs in its loop): it is cancelled there
            self._fired = True
            self.task.cancel()

    def fired(self) -> bool:
        """Whether the cancellation the waiting task caught is this timer's (then taken back: the task goes
        on to close its stream); False for any other, or when another came as well."""
        if not self._fired:
            return False
        self._fired = False
        uncancel = getattr(self.task, "uncancel", None)  # Python 3.11+: cancellations are counted
        return uncancel is None or uncancel() == 0

    def stop(self) -> None:
        self._handle.cancel()


class StreamSession:
    """Serve one WebSocket connection (see ``docs/live.md`` for the protocol).

    Parameters
    ----------
    state : gesturedb.serve.app.ServerState
        What all sessions share: the database, the limits, the stream factory, the result store.
    websocket : starlette.websockets.WebSocket
        Accepted already.
    """

    def __init__(self, state, websocket: WebSocket):
        self.state, self.ws = state, websocket
        self.limits = state.limits
        self.stream = None
        self.fmt = None
        self.sample_rate = None
        self.n_samples = 0
        self.total_samples = None  # what the start message said the speech's length is (None: not said)
        self.errors = 0
        self.n_sent = 0
        self.control = None
        self._roots: list[np.ndarray] = []
        self._rots: list[np.ndarray] = []
        self._steps: list[dict] = []
        self._unfed: list[bytes] = []  # audio messages received, not yet fed to the stream (see _push)
        self._step_at = 0  # samples in all before the stream's next step can be ready (see _push)
        self._idle = None

    # -- the loop -------------------------------------------------------------
    async def run(self) -> None:
        self._idle = _IdleTimer(self.limits.idle_s)
        try:
            await self._serve()
        except _Close as c:
            await self._close(c)
        except WebSocketDisconnect:
            pass  # the client left; its stream is dropped with it
        except Exception as exc:  # a bug in the synthesizer or here: this stream ends, the server goes on
            log.exception("stream failed")
            await self._close(_Close(P.CLOSE_INTERNAL, "internal", f"the synthesizer failed: {type(exc).__name__}: "
                                                                   f"{str(exc)[:300]}"))
        finally:
            self._idle.stop()
            if self.state.scheduler is not None and self.stream is not None:
                self.state.scheduler.forget(self.stream)

    async def _serve(self) -> None:
        start = await self._receive()
        await self._start(start)
        while True:
            msg = await self._receive()
            data = msg.get("bytes")
            if data is not None:
                await self._audio(data)
                continue
            req = await self._json(msg.get("text"))
            if req is None:
                continue
            kind = req.get("type")
            if kind == "control":
                await self._control(req)
            elif kind == "words":
                await self._words(req)
            elif kind == "end":
                await self._end()
                return
            elif kind == "ping":
                await self._send_json({"type": "pong", "frames": self.n_sent})
            else:
                await self._reject("bad_message", f"unknown message type {echo(kind)!s}; expected control, words, "
                                                  "end, ping or binary audio")

    async def _receive(self) -> dict:
        """The next client message, within the idle limit and the size limit."""
        idle = self._idle
        idle.waiting()
        try:
            msg = await self.ws.receive()
        except asyncio.CancelledError:
            if not idle.fired():
                raise  # not ours: the server is stopping, say
            raise _Close(P.CLOSE_POLICY, "idle", f"no message for {self.limits.idle_s:g} s; the stream is closed") \
                from None
        finally:
            idle.wait_since = None
        if msg["type"] == "websocket.disconnect":
            raise WebSocketDisconnect(msg.get("code", 1000))
        data = msg.get("bytes")
        if data is not None:
            size = len(data)
        else:
            text = msg.get("text") or ""
            size = len(text) if text.isascii() else len(text.encode("utf-8", "surrogatepass"))
        if size > self.limits.max_message_bytes:
            raise _Close(P.CLOSE_TOO_BIG, "too_big", f"message of {size} bytes; the limit is "
                                                     f"{self.limits.max_message_bytes} bytes (send audio in chunks)")
        return msg

    async def _json(self, text) -> dict | None:
        """The JSON object of a text message; None (and an error message to the client) for anything else."""
        try:
            req = json.loads(text)
            problem = None if isinstance(req, dict) else "a JSON object"
        except (TypeError, ValueError, RecursionError) as exc:
            req, problem = None, f"JSON text ({type(exc).__name__})"
        if problem is None:
            return req
        if self.stream is None:
            raise _Close(P.CLOSE_POLICY, "bad_message", f"expected a JSON start message; got {echo(text)}")
        await self._reject("bad_message", f"expected {problem} or binary audio; got {echo(text)}")
        return None

    # -- messages -------------------------------------------------------------
    async def _start(self, msg: dict) -> None:
        if "bytes" in msg and msg["bytes"] is not None:
            raise _Close(P.CLOSE_POLICY, "bad_message", f"expected a JSON start message first; got {len(msg['bytes'])} "
                                                        "bytes of binary data")
        req = await self._json(msg.get("text"))
        if req.get("type") != "start":
            raise _Close(P.CLOSE_POLICY, "bad_message", f"expected a start message first; got type {echo(req.get('type'))}")
        proto = req.get("protocol", P.PROTOCOL_VERSION)
        if proto != P.PROTOCOL_VERSION:
            raise _Close(P.CLOSE_POLICY, "bad_protocol", f"protocol {echo(proto)} requested; this server speaks "
                                                         f"{P.PROTOCOL_VERSION}")
        rate = req.get("sample_rate")
        if isinstance(rate, bool) or not isinstance(rate, int) or not P.MIN_SAMPLE_RATE <= rate <= P.MAX_SAMPLE_RATE:
            raise _Close(P.CLOSE_POLICY, "bad_rate", f"sample_rate: expected an integer from {P.MIN_SAMPLE_RATE} to "
                                                     f"{P.MAX_SAMPLE_RATE} Hz; got {echo(rate)}")
        fmt = req.get("format", "pcm16")
        if fmt not in P.AUDIO_FORMATS:
            raise _Close(P.CLOSE_POLICY, "bad_format", f"format: expected one of {', '.join(P.AUDIO_FORMATS)}; "
                                                       f"got {echo(fmt)}")
        control = req.get("control")
        try:
            control = self.state.check_control(control)
        except ParameterError as exc:
            raise _Close(P.CLOSE_POLICY, "bad_control", str(exc)) from None
        total = req.get("total_samples")  # the speech's length when the client knows it (a file): a hint
        if total is not None and (isinstance(total, bool) or not isinstance(total, int)
                                  or not 0 <= total <= self.limits.max_audio_s * rate):
            raise _Close(P.CLOSE_POLICY, "bad_start", f"total_samples: expected an integer from 0 to "
                                                      f"{int(self.limits.max_audio_s * rate)} (the limit of "
                                                      f"{self.limits.max_audio_s:g} s at {rate} Hz) or null; "
                                                      f"got {echo(total)}")
        if self.state.stream_factory is None:
            raise _Close(P.CLOSE_INTERNAL, "unavailable", self.state.stream_unavailable)
        self.fmt, self.sample_rate, self.total_samples = fmt, rate, total
        self.t_start = time.monotonic()
        try:
            self.stream = await run_in_threadpool(self.state.new_stream, rate, total)
        except GestureDBError as exc:
            raise _Close(P.CLOSE_POLICY, "bad_start", str(exc)) from None
        if self.state.scheduler is not None and hasattr(self.stream, "next_step"):
            self._step_at = self.stream.samples_before_step()
        if control is not None:
            await self._synth(self.stream.set_control, control)
        self.control = control
        if req.get("words") is not None:
            await self._words({"words": req["words"]})
        await self._ahead()
        sk = self.state.db.skeleton
        await self._send_json({
            "type": "ready", "protocol": P.PROTOCOL_VERSION, "layout": P.LAYOUT_VERSION,
            "fps": float(self.stream.fps), "sample_rate": rate, "format": fmt,
            "latency_s": float(self.stream.latency_s), "joints": sk.n_joints,
            "frame_floats": P.frame_width(sk.n_joints), "control": control,
            "limits": {"max_message_bytes": self.limits.max_message_bytes, "idle_s": self.limits.idle_s,
                       "max_audio_s": self.limits.max_audio_s},
        })

    async def _audio(self, data: bytes) -> None:
        t_recv = time.monotonic()  # this message's last sample is here: a step it completes is timed from now
        if self.stream is None:  # cannot happen: _start ran first; kept as a guard for refactors
            raise _Close(P.CLOSE_POLICY, "bad_message", "audio before the start message")
        try:
            n = P.audio_samples(data, self.fmt)
        except ParameterError as exc:
            await self._reject("bad_audio", str(exc))
            return
        self.n_samples += n
        if self.n_samples > self.limits.max_audio_s * self.sample_rate:
            raise _Close(P.CLOSE_POLICY, "too_long", f"the stream passed the limit of {self.limits.max_audio_s:g} s "
                                                     "of speech; start a new one")
        # faster than real time beyond the allowance: this stream waits (TCP pushes back on its client)
        ahead_s = self.n_samples / self.sample_rate - (time.monotonic() - self.t_start) - self.limits.max_ahead_s
        if ahead_s > 0:
            await anyio.sleep(ahead_s)
        if not n:
            return
        if self.n_samples < self._step_at:
            # no step can be ready yet: the bytes are fed later in one piece (the same features, fewer calls,
            # decoded once), and this message costs no trip to a worker thread
            self._unfed.append(data)
            return
        await self._send_chunk(await self._push(data), t_recv=t_recv)

    async def _push(self, data: bytes):
        """The stream's ``push`` of an audio message, with its steps searched by the server's scheduler
        together with the other streams' waiting steps (each applied here, to this stream only), when the
        server batches."""
        sched = self.state.scheduler
        if sched is None or not hasattr(self.stream, "next_step"):
            return await self._synth(self.stream.push, P.decode_audio(data, self.fmt))
        self._unfed.append(data)
        unfed, self._unfed = self._unfed, []
        chunk, up = await self._ready_steps((unfed, self.fmt))
        self._step_at = self.stream.samples_before_step()
        if up is not None:  # the coming step, pre-selected while its speech arrives
            sched.ahead(up)
        return chunk

    async def _ready_steps(self, held: tuple | None):
        """Feed ``held`` audio (see :func:`_advance`) and apply every step it made ready: ``(chunk, coming step
        or None)``. The feed and every step whose pre-selection is there (finished and applied) run in one call
        in the step thread, since on a loaded machine each hop to a thread and back waits longer than that
        work takes; a step without its pre-selection (under way, stale, none, a stream's last) is searched by
        the scheduler with the other streams' waiting steps."""
        sched = self.state.scheduler
        sq, chunk, up = await self._step(_advance, self.stream, sched, held, None)
        while sq is not None:
            res, relaxed = await self._closing(sched.search(sq))
            sq, chunk, up = await self._step(_advance, self.stream, sched, None, (sq, res, relaxed))
        return chunk, up

    async def _ahead(self) -> None:
        """Have the stream's coming step pre-selected now (its inputs changed: the start, a control)."""
        sched = self.state.scheduler
        if sched is not None and sched.ahead_enabled and hasattr(self.stream, "upcoming_step"):
            sched.ahead(await self._synth(self.stream.upcoming_step))

    async def _control(self, req: dict) -> None:
        try:
            control = self.state.check_control(req.get("control"))
        except ParameterError as exc:
            await self._reject("bad_control", f"{exc}; the stream keeps {echo(self.control)}")
            return
        try:
            await run_in_threadpool(self.stream.set_control, control)
        except GestureDBError as exc:
            await self._reject("bad_control", f"{exc}; the stream keeps {echo(self.control)}")
            return
        self.control = control
        await self._ahead()
        await self._send_json({"type": "control", "control": control, "from_frame": self.n_sent})

    async def _words(self, req: dict) -> None:
        try:
            words = check_words(req.get("words"))
        except ParameterError as exc:
            await self._reject("bad_words", str(exc))
            return
        if words:
            await self._synth(self.stream.push_words, words)
            await self._ahead()  # the coming step's keyword bitset may have changed

    async def _end(self) -> None:
        if self._unfed:  # audio held for the next step's feed (see _push): the stream needs it all now
            unfed, self._unfed = self._unfed, []
            await self._synth(_feed, self.stream, unfed, self.fmt)
        sched = self.state.scheduler
        if sched is not None:  # a scheduler only serves gesturedb's own Stream (ServerState), which has end_speech
            # the last steps (the speech's tail, the final one shorter) go through the scheduler like any step:
            # searched with the other streams' waiting steps, so that streams ending together share passes
            # over the database instead of one each (the ends of 50 streams within half a second were the
            # tail of the spread benchmark: docs/live-measurements.md, "While streaming")
            if self.n_samples != self.total_samples:
                # its coming step was pre-selected as a full one, for speech that will not come (a stream told
                # its length had its last, shorter step pre-selected: kept)
                sched.forget(self.stream)
            await self._synth(self.stream.end_speech)
            await self._send_chunk((await self._ready_steps(None))[0])
        await self._send_chunk(await self._synth(self.stream.finish))
        token = None
        if self.n_sent:
            token = self.state.results.put(self._result())
        await self._send_json({"type": "done", "frames": self.n_sent,
                               "result": None if token is None else f"/result/{token}"})
        await self._close(_Close(P.CLOSE_NORMAL))

    @staticmethod
    async def _closing(pending):
        """Await a synthesizer call; its deliberate errors (a control that leaves a step no candidate, say)
        end this stream with their message."""
        try:
            return await pending
        except GestureDBError as exc:
            raise _Close(P.CLOSE_POLICY, "synthesis", str(exc)) from None

    async def _synth(self, call, *args):
        """A synthesizer call in a worker thread (:meth:`_closing`)."""
        return await self._closing(run_in_threadpool(call, *args))

    async def _step(self, call, *args):
        """:meth:`_synth` in the scheduler's step thread, first come, first served
        (:meth:`~gesturedb.serve.batcher.StepScheduler.run_step`)."""
        return await self._closing(self.state.scheduler.run_step(call, *args))

    # -- out ------------------------------------------------------------------
    async def _send_chunk(self, chunk, *, t_recv: float | None = None) -> None:
        """Send a chunk's frames and steps; ``t_recv``: when the audio message that completed them arrived
        (its steps' server latency is counted from then to the send)."""
        motion = getattr(chunk, "motion", None)
        steps = list(getattr(chunk, "steps", None) or [])
        n = 0 if motion is None else int(motion.rotations.shape[0])
        if n == 0 and not steps:
            return
        J = self.state.db.skeleton.n_joints
        root = np.zeros((0, 3), np.float32) if n == 0 else np.asarray(motion.root_positions, np.float32)
        rot = np.zeros((0, J, 4), np.float32) if n == 0 else np.asarray(motion.rotations, np.float32)
        start = int(getattr(chunk, "start", self.n_sent))
        await self.ws.send_bytes(P.pack_frames(start, root, rot, steps, samples=self.n_samples))
        if t_recv is not None and steps:
            self.state.step_latency.add(time.monotonic() - t_recv, len(steps))
        if n:  # kept as the synthesizer made them (float64): the download is its motion, not a rounded copy
            self._roots.append(np.asarray(motion.root_positions))
            self._rots.append(np.asarray(motion.rotations))
            self.n_sent = start + n
        self._steps.extend(P.json_safe(steps))

    def _result(self):
        return {"motion": Motion(self.state.db.skeleton, float(self.stream.fps), np.concatenate(self._rots),
                                 np.concatenate(self._roots)),
                "steps": self._steps}

    async def _send_json(self, obj: dict) -> None:
        await self.ws.send_text(json.dumps(P.json_safe(obj), allow_nan=False))

    async def _reject(self, code: str, message: str) -> None:
        """A message refused; the stream goes on (until too many are)."""
        self._count_error()
        await self._send_json({"type": "error", "code": code, "message": message, "fatal": False})

    def _count_error(self) -> None:
        self.errors += 1
        if self.errors > self.limits.max_errors:
            raise _Close(P.CLOSE_POLICY, "too_many_errors", f"more than {self.limits.max_errors} rejected messages; "
                                                            "the stream is closed")

    async def _close(self, c: _Close) -> None:
        if self.ws.client_state != WebSocketState.CONNECTED:
            return
        try:
            if c.code_name is not None:
                log.info("stream closed: %s: %s", c.code_name, c.message)
                await self._send_json({"type": "error", "code": c.code_name, "message": c.message, "fatal": True})
            # a close reason is at most 123 bytes (RFC 6455)
            reason = (c.code_name or "")[:123]
            await self.ws.close(code=c.close_code, reason=reason)
        except (WebSocketDisconnect, RuntimeError, OSError):
            pass  # the client is gone already


def _feed(stream, messages: list[bytes], fmt: str) -> None:
    """Feed held audio messages to ``stream`` in one piece: decoded once, joined (the same samples as each
    message decoded in turn, :func:`~gesturedb.serve.protocol.audio_samples` having checked each)."""
    stream.feed(P.decode_audio(messages[0] if len(messages) == 1 else b"".join(messages), fmt))


def _advance(stream, sched, held: tuple | None, done: tuple | None):
    """Feed held audio (``held``: ``(messages, fmt)``, see :func:`_feed`) or apply a searched step (``done``:
    ``(sq, res, relaxed)``), then finish
    and apply each ready step whose pre-selection is there (:meth:`StepScheduler.finish_ready`), all in the
    calling thread. Returns ``(step or None, chunk or None, coming step or None)``: the next ready step that
    needs the scheduler's :meth:`~StepScheduler.search`, or else the chunk of frames made final and, once a
    step was applied and the scheduler pre-selects, the coming step prepared without its speech
    (:meth:`~gesturedb.synth.matching.Stream.upcoming_step`)."""
    if held is not None:
        _feed(stream, *held)
    applied = done is not None
    if applied:
        stream.complete_step(*done)
    while (sq := stream.next_step()) is not None:
        got = sched.finish_ready(sq)
        if got is None:
            return sq, None, None
        stream.complete_step(sq, *got)
        applied = True
    return None, stream.take_chunk(), (stream.upcoming_step() if applied and sched.ahead_enabled else None)


def check_words(words) -> list[tuple[float, float, str]]:
    """``[[start_s, end_s, text], ...]`` from a client, checked: finite times, end >= start, short text.

    Raises
    ------
    ParameterError
    """
    if not isinstance(words, list):
        raise ParameterError(f"words: expected a list of [start_s, end_s, text]; got {echo(words)}")
    if len(words) > MAX_WORDS_PER_MESSAGE:
        raise ParameterError(f"words: expected at most {MAX_WORDS_PER_MESSAGE} words per message; got {len(words)}")
    out = []
    for i, w in enumerate(words):
        ok = (isinstance(w, (list, tuple)) and len(w) == 3 and isinstance(w[2], str) and len(w[2]) <= MAX_WORD_CHARS
              and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in w[:2])
              and 0 <= w[0] <= w[1])
        if not ok:
            raise ParameterError(f"words[{i}]: expected [start_s, end_s, text] with 0 <= start_s <= end_s and text of "
                                 f"at most {MAX_WORD_CHARS} characters; got {echo(w)}")
        out.append((float(w[0]), float(w[1]), w[2]))
    return out
