"""The ASGI app of ``gesturedb serve``: one open database, many clients.

=========================  =====================================================
``GET  /``                 the browser studio (``studio/``), three.js from Debian
``GET  /health``           status, database, whether streaming is available
``GET  /skeleton``         joint names, parents, rest offsets (metres), fps
``GET  /controls``         the database's control features and saved masks
``GET  /source``           a stretch of a database recording as a frames message (``format=wav``: its speech)
``POST /synth``            a WAV (and a transcript) -> BVH, glb, npz, JSON or frames
``GET  /result/{token}``   a finished stream's motion as BVH, glb or npz
``WS   /stream``           live: audio and controls in, frames and provenance out
=========================  =====================================================

The protocol is in ``docs/live.md`` and :mod:`gesturedb.serve.protocol`. Nothing
a client sends names a file: uploads go to a private temporary folder under
names chosen here, recordings are named as the database names them.
"""
from __future__ import annotations

import inspect
import io
import json
import logging
import os
import re
import secrets
import tempfile
import threading
import time
import wave
from collections import OrderedDict, deque
from urllib.parse import urlsplit

import numpy as np
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, RedirectResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket

from gesturedb._version import __version__
from gesturedb.control.compile import compile_mask
from gesturedb.control.schedule import parse_schedule
from gesturedb.errors import GestureDBError, ParameterError, echo
from gesturedb.io import write_motion
from gesturedb.io.audio import audio_duration, read_audio
from gesturedb.search import blocked_min_queries
from gesturedb.serve import protocol as P
from gesturedb.serve.batcher import StepScheduler
from gesturedb.serve.limits import Limits
from gesturedb.serve.session import StreamSession
from gesturedb.serve.vendor import find_gltf_loader, find_three
from gesturedb.synth.matching import Searcher

log = logging.getLogger("gesturedb.serve")

STUDIO_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "studio")
#: Formats of ``POST /synth`` and ``GET /result``: name -> media type.
OFFLINE_FORMATS = {"bvh": "text/plain; charset=utf-8", "glb": "model/gltf-binary", "npz": "application/zip",
                   "json": "application/json", "frames": "application/octet-stream"}
RESULT_FORMATS = ("bvh", "glb", "npz", "frames")
#: Transcript formats ``POST /synth`` reads, by the extension of the uploaded file's name.
TRANSCRIPT_EXTENSIONS = (".textgrid", ".tsv", ".json")
#: Longest control expression a client may send, characters.
MAX_CONTROL_CHARS = 2000
_TOKEN = re.compile(r"^[0-9a-f]{32}$")


def default_stream_factory():
    """The streaming synthesizer class and None, or None and why it is not available."""
    try:
        # local on purpose: probes whether the live path is installed; an ImportError becomes the message below
        from gesturedb.synth.stream import Stream
    except ImportError as exc:
        return None, (f"live streaming is not available in this installation: gesturedb.synth.stream could not be "
                      f"imported ({exc}); POST /synth still works")
    return Stream, None


class ResultStore:
    """Finished streams' results, kept for download for a while: at most ``size``, each ``ttl_s`` seconds."""

    def __init__(self, size: int, ttl_s: float):
        self.size, self.ttl_s = size, ttl_s
        self._items: OrderedDict[str, tuple[float, dict]] = OrderedDict()
        self._lock = threading.Lock()

    def put(self, result: dict) -> str:
        token = secrets.token_hex(16)
        with self._lock:
            self._expire()
            self._items[token] = (time.monotonic(), result)
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return token

    def get(self, token: str) -> dict | None:
        with self._lock:
            self._expire()
            item = self._items.get(token)
        return None if item is None else item[1]

    def _expire(self) -> None:
        now = time.monotonic()
        for k in [k for k, (t, _) in self._items.items() if now - t > self.ttl_s]:
            del self._items[k]


class StepLatency:
    """The server's share of each streamed step's latency: seconds from the arrival of the audio message that
    completed the step's speech to the send of its frames (issue 39's measure, "from the last audio sample of
    a step's window to its frames being sent"; what a client measures adds the network and its own
    scheduling). The latest ``keep`` steps are kept; every touch is on the event loop's thread."""

    def __init__(self, keep: int = 100_000):
        self._s: deque[float] = deque(maxlen=keep)
        self.n = 0

    def add(self, seconds: float, steps: int = 1) -> None:
        self._s.extend([float(seconds)] * int(steps))
        self.n += int(steps)

    def summary(self, last: int | None = None) -> dict:
        """``steps`` (all so far), ``over`` (the latest steps summarised: ``last``, or all kept) and their
        ``p50_ms``, ``p99_ms``, ``max_ms`` (None before any step)."""
        x = np.fromiter(self._s, dtype=np.float64, count=len(self._s))
        if last is not None:
            x = x[max(0, x.size - int(last)):]
        q = (np.percentile(x, [50, 99]) * 1000).tolist() if x.size else [None, None]
        return {"steps": self.n, "over": int(x.size), "p50_ms": q[0], "p99_ms": q[1],
                "max_ms": float(x.max() * 1000) if x.size else None}


class ServerState:
    """What every request and stream shares: the database (opened once), limits, the synthesizers."""

    def __init__(self, db, limits: Limits, stream_factory, *, batch_steps: bool = True, ahead: bool = True):
        self.db = db
        self.limits = limits
        why = None
        #: the scheduler that searches the waiting steps of every stream in one call (None: each alone)
        self.scheduler = None
        self._default_factory = stream_factory is None
        if stream_factory is None:
            stream_factory, why = default_stream_factory()
            if stream_factory is not None and "searcher" in inspect.signature(stream_factory).parameters:
                cls = stream_factory
                # one Searcher (segments, pose projection) serves every stream instead of one each
                stream_factory = lambda d, *, sample_rate, n_samples=None: cls(  # noqa: E731
                    d, sample_rate=sample_rate, n_samples=n_samples, searcher=self.searcher())
        self.stream_factory, self.stream_unavailable = stream_factory, why
        # whether the factory takes the speech's length a client may tell (gesturedb's own Stream does)
        self._takes_length = stream_factory is not None and "n_samples" in inspect.signature(stream_factory).parameters
        self.results = ResultStore(limits.max_results, limits.result_ttl_s)
        self.streams = 0
        self.step_latency = StepLatency()
        self.three = find_three()
        self._controls_ok: OrderedDict[str, None] = OrderedDict()
        self._control_lock = threading.Lock()
        self._offline_lock = threading.Lock()
        self._searcher = None
        if batch_steps and stream_factory is not None and why is None and self._default_factory:
            self.scheduler = StepScheduler(self.searcher(), ahead=ahead)

    def check_control(self, control) -> str | None:
        """A client's control: None (no control), a mask expression or saved mask name, or a schedule of
        them over output seconds (``"0-12: left_wrist_high; 12-: symmetric"``), every expression of
        which compiles against this database.

        Raises
        ------
        ParameterError
            Not a string, too long, or an expression the database cannot compile (the message says why).
        """
        if control is None or control == "":
            return None
        if not isinstance(control, str) or len(control) > MAX_CONTROL_CHARS:
            raise ParameterError(f"control: expected a mask expression or mask name of at most {MAX_CONTROL_CHARS} "
                                 f"characters, or null; got {echo(control)}")
        with self._control_lock:
            if control in self._controls_ok:
                return control

            db = self.db
            exprs = [item.expr for item in parse_schedule(control)] if ":" in control else [control]
            for expr in exprs:
                compile_mask(expr, controls=db.control_datasets, named=db.mask_datasets, units=db.control_units,
                             n_frames=db.n_frames)
            self._controls_ok[control] = None
            while len(self._controls_ok) > 256:
                self._controls_ok.popitem(last=False)
        return control

    def new_stream(self, sample_rate: int, n_samples: int | None = None):
        """A client's stream; ``n_samples``, its speech's length when the client told it, goes to factories that
        take it (gesturedb's own Stream: its last step pre-selected ahead like the others)."""
        if n_samples is not None and self._takes_length:
            return self.stream_factory(self.db, sample_rate=sample_rate, n_samples=n_samples)
        return self.stream_factory(self.db, sample_rate=sample_rate)

    def searcher(self):
        """The k-NN Searcher every stream and upload shares (built once: its segments and pose projection)."""
        with self._control_lock:
            if self._searcher is None:
                self._searcher = Searcher(self.db)
        return self._searcher

    def warm(self) -> float:
        """Pay before the first client what its first step would pay: the searcher's pose projection, and a
        stream through a second of quiet noise (the audio features' JIT compilation, the database's floor
        and accelerations: 9 s on the first stream of a process, 2 ms on the next). Seconds taken."""
        t = time.perf_counter()
        self.searcher().pose_projection()
        if self.stream_factory is not None:
            try:
                s = self.stream_factory(self.db, sample_rate=16000)
                noise = np.random.default_rng(0).normal(0, 0.01, 24000).astype(np.float32)
                if self.scheduler is not None:
                    # and the batched search's set-up: its tables, the blocked kernel's pass over the
                    # database (copies of a step: the smallest batch that takes the blocked path)
                    s.feed(noise)
                    sq = s.next_step()
                    self.scheduler.batch.search([sq] * blocked_min_queries(self.scheduler.batch.threads))
                    s.complete_step(sq, *self.scheduler.batch.search([sq])[0])
                else:
                    s.push(noise)
                s.finish()
            except Exception as exc:  # a stream that cannot start says so to its client; the server serves on
                log.warning("warming up the streaming synthesizer failed: %s: %s", type(exc).__name__, exc)
        return time.perf_counter() - t

    def synthesize(self, wav: bytes, transcript: tuple[str, bytes] | None, control: str | None, seed: int):
        """Offline synthesis of an uploaded WAV, one at a time (the streams keep the other core)."""

        with tempfile.TemporaryDirectory(prefix="gesturedb-serve-") as tmp, self._offline_lock:
            audio = os.path.join(tmp, "speech.wav")
            with open(audio, "wb") as f:
                f.write(wav)
            words = None
            if transcript is not None:
                words = os.path.join(tmp, "words" + transcript[0])
                with open(words, "wb") as f:
                    f.write(transcript[1])
            try:
                dur = audio_duration(audio)
                if dur > self.limits.max_audio_s:
                    raise ParameterError(f"audio: {dur:.1f} s of speech; the limit is {self.limits.max_audio_s:g} s")
                return self.searcher().synthesize(audio, transcript=words, control=control, seed=seed)
            except GestureDBError as exc:
                # the temporary folder is no business of the client's
                raise ParameterError(str(exc).replace(tmp + os.sep, "").replace(tmp, "upload")) from None


class BodyTooLarge(Exception):
    pass


class _BodyLimit:
    """ASGI middleware: an HTTP request body over ``limit`` bytes is refused (413) before it is kept,
    whether it declares its length or is sent chunked."""

    def __init__(self, app, limit: int):
        self.app, self.limit = app, limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > self.limit):
            resp = JSONResponse({"error": "too_big", "message": f"request body of {declared.decode(errors='replace')}"
                                 f" bytes; the limit is {self.limit} bytes"}, status_code=413)
            return await resp(scope, receive, send)
        seen = 0

        async def limited():
            nonlocal seen
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > self.limit:
                    raise BodyTooLarge(f"request body over the limit of {self.limit} bytes")
            return msg

        return await self.app(scope, limited, send)


def _error(status: int, code: str, message: str) -> JSONResponse:
    return JSONResponse({"error": code, "message": message}, status_code=status)


def _same_origin(headers, scope) -> bool:
    """True when a browser request comes from a page of this server (or from no browser at all):
    a web page elsewhere must not drive the local server through the user's browser."""
    origin = headers.get("origin")
    if origin is None:
        return True
    return urlsplit(origin).netloc == headers.get("host", "")


def create_app(db, *, limits: Limits | None = None, stream_factory=None, batch_steps: bool = True,
               ahead: bool = True) -> Starlette:
    """The ASGI app serving ``db`` (an open :class:`gesturedb.db.database.Database`).

    Parameters
    ----------
    db : Database
        Opened once by the caller and shared by every client (read only).
    limits : Limits, optional
    stream_factory : callable, optional
        ``factory(db, sample_rate=...)`` -> a streaming synthesizer with ``push``,
        ``push_words``, ``set_control``, ``finish``, ``fps`` and ``latency_s``;
        default :class:`gesturedb.synth.stream.Stream`.
    batch_steps : bool
        Search the steps that concurrent streams wait on in one call
        (:class:`gesturedb.serve.batcher.StepScheduler`; the same frames, less time per step with
        many streams); False: each stream searches its own. Only for the default ``stream_factory``.
    ahead : bool
        With ``batch_steps``, pre-select each stream's coming step by pose while its speech arrives
        (:mod:`gesturedb.serve.batcher`; the same frames, a shorter search once the speech has come).
    """
    limits = limits or Limits()
    state = ServerState(db, limits, stream_factory, batch_steps=batch_steps, ahead=ahead)
    state.warm_s = state.warm()
    state.gltf_loader = find_gltf_loader(state.three)  # the studio's own character (a .glb the user picks)
    if state.three is None:
        log.warning("three.js not found (Debian's libjs-three, /usr/share/javascript/three/three.module.js): the "
                    "studio page loads but cannot draw the body; install it with `apt-get install libjs-three`")
    if state.stream_factory is None:
        log.warning("%s", state.stream_unavailable)

    async def health(request: Request):
        last = request.query_params.get("last")
        if last is not None and not (last.isdigit() and int(last) > 0):
            return _error(400, "bad_query", f"last: expected a number of steps >= 1; got {echo(last)}")
        return JSONResponse({
            "status": "ok", "version": __version__, "database": os.path.basename(str(db.path)),
            "fps": float(db.fps), "frames": int(db.n_frames), "joints": db.skeleton.n_joints,
            "stream": state.stream_factory is not None, "stream_error": state.stream_unavailable,
            "streams": state.streams, "pid": os.getpid(), "three_js": state.three is not None, "protocol": P.PROTOCOL_VERSION,
            "batch": None if state.scheduler is None else state.scheduler.stats(),
            "gltf_loader": state.gltf_loader is not None,
            # the server's share of the streamed steps' latency (all steps, or the latest `?last=N`)
            "step_latency": state.step_latency.summary(None if last is None else int(last)),
        })

    async def skeleton(request: Request):
        sk = db.skeleton
        return JSONResponse({"names": list(sk.names), "parents": sk.parents.tolist(),
                             "offsets": np.round(sk.offsets, 6).tolist(), "fps": float(db.fps),
                             "rest_positions": np.round(sk.rest_positions(), 6).tolist(),
                             "layout": P.LAYOUT_VERSION, "frame_floats": P.frame_width(sk.n_joints)})

    async def controls(request: Request):
        units = db.control_units
        return JSONResponse({"controls": [{"name": k, "unit": units.get(k, "")} for k in sorted(db.control_datasets)],
                             "masks": [{"name": k, "definition": v} for k, v in db.mask_definitions.items()],
                             "recordings": [r.name for r in db.recordings]})

    async def source(request: Request):
        q = request.query_params
        fmt = q.get("format", "frames")
        if fmt not in ("frames", "wav"):
            return _error(400, "bad_format", f"format: expected frames or wav; got {echo(fmt)}")
        try:
            start_s, end_s = float(q.get("start_s", "0")), float(q.get("end_s", "nan"))
            if not (0 <= start_s < end_s and end_s - start_s <= limits.max_source_s):
                raise ParameterError(f"start_s, end_s: expected 0 <= start_s < end_s <= start_s + "
                                     f"{limits.max_source_s:g}; got {echo(q.get('start_s'))}, {echo(q.get('end_s'))}")
            db.frame_range(q.get("recording", ""), start_s, end_s)  # the same checks for both formats
            if fmt == "wav":
                path = _source_speech_path(db, q.get("recording", ""))
                if path is None:
                    rec = db.recording(q.get("recording", ""))
                    return _error(404, "no_audio", f"recording {rec.name!r}: its speech file {rec.audio_path!r} "
                                                   f"(as the build was given it) is not on this server")
                wav = await run_in_threadpool(_speech_stretch, path, start_s, end_s)
                return Response(wav, media_type="audio/wav")
            motion = await run_in_threadpool(db.motion, q.get("recording", ""), start_s, end_s)
        except (ValueError, GestureDBError) as exc:
            return _error(400, "bad_request", str(exc))
        return Response(P.pack_frames(0, motion.root_positions, motion.rotations),
                        media_type="application/octet-stream")

    async def synth(request: Request):
        if not _same_origin(request.headers, request.scope):
            return _error(403, "origin", "requests from pages of other sites are refused")
        q = request.query_params
        fmt = q.get("format", "bvh")
        if fmt not in OFFLINE_FORMATS:
            return _error(400, "bad_format", f"format: expected one of {', '.join(OFFLINE_FORMATS)}; got {echo(fmt)}")
        try:
            control = state.check_control(q.get("control"))
            seed = q.get("seed", "0")
            if not (seed.isdigit() and int(seed) < 2**63):
                raise ParameterError(f"seed: expected an integer from 0 to 2**63-1; got {echo(seed)}")
        except ParameterError as exc:
            return _error(400, "bad_request", str(exc))
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        transcript = None
        if ctype == "multipart/form-data":
            form = await request.form(max_files=2, max_fields=2)
            audio = form.get("audio")
            if not isinstance(audio, UploadFile):
                return _error(400, "bad_request", "multipart: expected a file field 'audio' (a WAV)")
            wav = await audio.read()
            t = form.get("transcript")
            if isinstance(t, UploadFile):
                ext = os.path.splitext(t.filename or "")[1].lower()
                if ext not in TRANSCRIPT_EXTENSIONS:
                    return _error(400, "bad_request", f"transcript: expected a file named *.TextGrid, *.tsv or *.json; "
                                                      f"got {echo(t.filename)}")
                transcript = (".TextGrid" if ext == ".textgrid" else ext, await t.read())
            elif t is not None:
                return _error(400, "bad_request", "transcript: expected a file field (*.TextGrid, *.tsv, *.json)")
        elif ctype in ("audio/wav", "audio/x-wav", "audio/wave", "application/octet-stream"):
            wav = await request.body()
        else:
            return _error(415, "bad_media_type", f"expected multipart/form-data with 'audio' (and 'transcript') or an "
                                                 f"audio/wav body; got {echo(ctype)}")
        try:
            res = await run_in_threadpool(state.synthesize, wav, transcript, control, int(seed))
        except ParameterError as exc:
            return _error(400, "bad_input", str(exc))
        if fmt == "json":
            return JSONResponse(P.json_safe(res.provenance()))
        return await _motion_response(res.motion, fmt, P.json_safe(res.steps))

    async def result(request: Request):
        token = request.path_params["token"]
        fmt = request.query_params.get("format", "bvh")
        item = state.results.get(token) if _TOKEN.match(token) else None
        if item is None:
            return _error(404, "not_found", f"no result {echo(token)} (results are kept {limits.result_ttl_s:g} s)")
        if fmt not in RESULT_FORMATS:
            return _error(400, "bad_format", f"format: expected one of {', '.join(RESULT_FORMATS)}; got {echo(fmt)}")
        return await _motion_response(item["motion"], fmt, item["steps"])

    async def _motion_response(motion, fmt: str, steps) -> Response:
        data = await run_in_threadpool(_encode_motion, motion, fmt, steps)
        headers = {} if fmt == "frames" else {"content-disposition": f'attachment; filename="gesturedb.{fmt}"'}
        return Response(data, media_type=OFFLINE_FORMATS[fmt], headers=headers)

    async def stream(websocket: WebSocket):
        if not _same_origin(websocket.headers, websocket.scope):
            await websocket.close(code=P.CLOSE_POLICY, reason="origin: pages of other sites may not connect")
            return
        await websocket.accept()
        if state.streams >= limits.max_streams:
            await websocket.send_text(json.dumps({"type": "error", "code": "busy", "fatal": True,
                                                  "message": f"the server holds its maximum of {limits.max_streams} "
                                                             "streams; try again later"}))
            await websocket.close(code=P.CLOSE_TRY_LATER, reason="busy")
            return
        state.streams += 1
        try:
            await StreamSession(state, websocket).run()
        finally:
            state.streams -= 1

    async def three(request: Request):
        if state.three is None:
            return PlainTextResponse("three.js not found: install Debian's libjs-three (apt-get install libjs-three)",
                                     status_code=404)
        return FileResponse(state.three, media_type="text/javascript")

    async def gltf_loader(request: Request):
        # served where its own import ("../../../build/three.module.js") finds the page's three.js
        if state.gltf_loader is None:
            return PlainTextResponse("three.js's GLTFLoader not found: install Debian's libjs-three "
                                     "(examples/jsm/loaders/GLTFLoader.js)", status_code=404)
        return FileResponse(state.gltf_loader, media_type="text/javascript")

    async def too_large(request: Request, exc: BodyTooLarge):
        return _error(413, "too_big", str(exc))

    routes = [
        Route("/", lambda request: RedirectResponse("/studio/index.html")),
        Route("/health", health),
        Route("/skeleton", skeleton),
        Route("/controls", controls),
        Route("/source", source),
        Route("/synth", synth, methods=["POST"]),
        Route("/result/{token}", result),
        Route("/vendor/three.module.js", three),
        # Debian's layout under /vendor/three/, so that the loader's relative import is the page's three.js
        Route("/vendor/three/build/three.module.js", three),
        Route("/vendor/three/examples/jsm/loaders/GLTFLoader.js", gltf_loader),
        WebSocketRoute("/stream", stream),
        Mount("/studio", StaticFiles(directory=STUDIO_DIR), name="studio"),
    ]
    app = Starlette(routes=routes, exception_handlers={BodyTooLarge: too_large},
                    middleware=[Middleware(_BodyLimit, limit=limits.max_upload_bytes)])
    app.state.gesturedb = state
    return app


def _source_speech_path(db, recording: str) -> str | None:
    """The speech file of a database recording on this machine, or None: the path the build was given,
    as is when absolute, else from the server's working folder or the database's folder."""
    given = db.recording(recording).audio_path
    if not given:
        return None
    tries = [given] if os.path.isabs(given) else [given, os.path.join(os.path.dirname(os.path.abspath(db.path)), given)]
    return next((p for p in tries if os.path.isfile(p)), None)


def _speech_stretch(path: str, start_s: float, end_s: float) -> bytes:
    """Seconds ``[start_s, end_s)`` of a speech file as a mono PCM16 WAV at the file's own rate (what a
    browser decodes); the recording's frame ``i`` is at ``i / fps`` s of its speech, as the build paired them."""
    x, sr = read_audio(path, sr=None)
    a, b = int(round(start_s * sr)), int(round(end_s * sr))
    pcm = (np.clip(x[a:b], -1.0, 1.0) * 32767.0).round().astype("<i2")
    buf = io.BytesIO()
    with wave.open(buf, "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(int(sr))
        w.writeframes(pcm.tobytes())
    return buf.getvalue()


def _encode_motion(motion, fmt: str, steps) -> bytes:
    if fmt == "frames":
        return P.pack_frames(0, motion.root_positions, motion.rotations, steps)
    if fmt == "npz":
        buf = io.BytesIO()
        sk = motion.skeleton
        np.savez_compressed(buf, positions=motion.positions.astype(np.float32),
                            rotations=motion.rotations.astype(np.float32),
                            root_positions=motion.root_positions.astype(np.float32), fps=motion.fps,
                            parents=np.asarray(sk.parents), names=np.asarray(sk.names), offsets=sk.offsets)
        return buf.getvalue()

    with tempfile.TemporaryDirectory(prefix="gesturedb-serve-") as tmp:
        path = os.path.join(tmp, "result." + fmt)
        write_motion(path, motion)
        with open(path, "rb") as f:
            return f.read()
