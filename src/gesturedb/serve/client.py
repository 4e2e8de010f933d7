"""A small client of ``gesturedb serve`` for the engine side: speech in, poses out.

    from gesturedb.serve.client import LiveClient

    with LiveClient("ws://127.0.0.1:8765/stream", sample_rate=48000, format="f32") as live:
        sk = live.skeleton()                   # names, parents, offsets (metres)
        while talking:
            live.send_audio(mic_block)         # float32 mono in [-1, 1], any length
            for fr in live.poll():             # frames that are final now, never blocks
                for i in range(len(fr)):       # frame fr.start + i, at (fr.start + i) / live.fps s
                    pose(fr.root_positions[i], fr.rotations[i])   # (3,) metres; (J, 4) local w, x, y, z
        live.set_control("left_wrist_height_high")   # from the next search step on
        rest = live.end()                      # the last frames; live.result_url downloads them all

Only numpy and the ``websockets`` package (its synchronous client); no server
code. The wire format is :mod:`gesturedb.serve.protocol`; ``docs/live.md``
describes it for clients in other languages. ``synthesize_file`` posts a WAV
for an offline result.
"""
from __future__ import annotations

import json
import os
import secrets
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from urllib.parse import urlencode, urlsplit, urlunsplit

import numpy as np

from gesturedb.errors import GestureDBError, ParameterError
from gesturedb.serve import protocol as P

#: Largest message the client accepts from the server (a long stream's last frames), bytes.
MAX_INCOMING_BYTES = 256 << 20


class LiveError(GestureDBError):
    """The server ended the stream; ``code`` is its error code (``bad_rate``, ``idle``, ...)."""

    def __init__(self, code: str, message: str):
        super().__init__(f"{code}: {message}")
        self.code, self.message = code, message


@dataclass
class Frames:
    """Consecutive output frames and the provenance of the steps they complete.

    Attributes
    ----------
    start : int
        Output frame index of ``root_positions[0]``; frame ``i`` plays at ``i / fps`` s of the speech.
    root_positions : ndarray [shape=(F, 3)], float32, metres (y up)
    rotations : ndarray [shape=(F, J, 4)], float32
        Local unit quaternions (w, x, y, z) per joint, in the order of ``skeleton()["names"]``.
    steps : list of dict
        One per search step completed here: recording, source_start_s, ranks, control, ...
    samples : int
        Audio samples the server had received when these frames became final: they answer the
        audio message that brought its count there (how a client measures its latency).
    """

    start: int
    root_positions: np.ndarray
    rotations: np.ndarray
    steps: list = field(default_factory=list)
    samples: int = 0

    def __len__(self) -> int:
        return int(self.root_positions.shape[0])


def http_url(ws_url: str, path: str) -> str:
    """The HTTP address of ``path`` on the server of a ``ws://`` stream address."""
    u = urlsplit(ws_url)
    return urlunsplit(("https" if u.scheme == "wss" else "http", u.netloc, path, "", ""))


class LiveClient:
    """One live stream to ``gesturedb serve``.

    Parameters
    ----------
    url : str
        ``ws://HOST:PORT/stream``.
    sample_rate : int
        Rate of the audio you will send, Hz (8000 to 192000); the server resamples.
    format : {"pcm16", "f32"}
        How samples travel: 16-bit integers (half the bytes) or float32.
    control : str, optional
        A mask expression or saved mask name in force from the first step.
    words : list of (start_s, end_s, text), optional
        Word timings known in advance (for keyword sub-databases).
    total_samples : int, optional
        The speech's whole length in samples, when you know it before sending it all (a file or a
        line of dialogue): the server then prepares the last step ahead like the others, and it
        costs it a millisecond instead of a pass over the database. The frames are the same either way.
    timeout_s : float
        How long to wait for the server to answer the start, and in :meth:`end`.
    """

    def __init__(self, url: str = "ws://127.0.0.1:8765/stream", *, sample_rate: int = 16000, format: str = "pcm16",
                 control: str | None = None, words=None, total_samples: int | None = None, timeout_s: float = 30.0):
        if format not in P.AUDIO_FORMATS:
            raise ParameterError(f"format: expected one of {', '.join(P.AUDIO_FORMATS)}; got {format!r}")
        self.url, self.sample_rate, self.format = url, int(sample_rate), format
        self.timeout_s = float(timeout_s)
        self.errors: list[dict] = []     # messages the server refused; the stream went on
        self.events: list[dict] = []     # control acknowledgements and other notices
        self.result_url: str | None = None
        self.done: dict | None = None
        self._ws = None
        self._start = {"type": "start", "protocol": P.PROTOCOL_VERSION, "sample_rate": self.sample_rate,
                       "format": format, "control": control}
        if total_samples is not None:
            self._start["total_samples"] = int(total_samples)
        if words is not None:
            self._start["words"] = [[float(a), float(b), str(t)] for a, b, t in words]
        self.ready: dict | None = None

    # -- connection -------------------------------------------------------------
    def connect(self) -> "LiveClient":
        """Open the stream and wait for the server's ``ready`` (fps, latency, joints)."""
        from websockets.sync.client import connect

        # entered as a context manager (websockets 17 asks it of a connection; close() exits it)
        self._ws = connect(self.url, max_size=MAX_INCOMING_BYTES, open_timeout=self.timeout_s).__enter__()
        self._ws.send(json.dumps(self._start))
        while self.ready is None:
            self._handle(self._recv(self.timeout_s), [])
        return self

    def __enter__(self) -> "LiveClient":
        return self.connect() if self._ws is None else self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._ws is not None:
            self._ws.close()
            self._ws = None

    @property
    def fps(self) -> float:
        return float(self.ready["fps"])

    @property
    def latency_s(self) -> float:
        """Algorithmic latency: audio a frame waits for before it is final, seconds."""
        return float(self.ready["latency_s"])

    def skeleton(self) -> dict:
        """``GET /skeleton``: names, parents, offsets (metres), fps."""
        with urllib.request.urlopen(http_url(self.url, "/skeleton"), timeout=self.timeout_s) as r:
            return json.loads(r.read())

    # -- in ---------------------------------------------------------------------
    def send_audio(self, samples) -> None:
        """Send mono samples (float in [-1, 1]; int16 is taken as PCM16) of any length."""
        x = np.asarray(samples)
        if x.dtype == np.int16:
            x = x.astype(np.float32) / 32768.0
        x = x.reshape(-1)
        per_message = self.ready["limits"]["max_message_bytes"] // P.AUDIO_FORMATS[self.format].itemsize
        for a in range(0, x.shape[0], per_message):
            self._ws.send(P.encode_audio(x[a:a + per_message], self.format))

    def set_control(self, control: str | None) -> None:
        """Switch the control (a mask expression, a saved mask name, or None) from the next step on."""
        self._ws.send(json.dumps({"type": "control", "control": control}))

    def send_words(self, words) -> None:
        """Word timings ``(start_s, end_s, text)`` as they become known."""
        self._ws.send(json.dumps({"type": "words", "words": [[float(a), float(b), str(t)] for a, b, t in words]}))

    # -- out --------------------------------------------------------------------
    def poll(self, timeout_s: float = 0.0) -> list[Frames]:
        """Frames received so far (waiting up to ``timeout_s`` for the first); never more than arrived."""
        out: list[Frames] = []
        msg = self._recv(timeout_s)
        while msg is not None:
            self._handle(msg, out)
            msg = self._recv(0.0)
        return out

    def end(self) -> list[Frames]:
        """Say the speech is over; returns the frames still to come (the server then closes the stream)."""
        self._ws.send(json.dumps({"type": "end"}))
        out: list[Frames] = []
        while self.done is None:
            msg = self._recv(self.timeout_s)
            if msg is None:
                raise LiveError("timeout", f"no answer to end within {self.timeout_s:g} s")
            self._handle(msg, out)
        self.close()
        return out

    def result(self, format: str = "bvh") -> bytes:
        """The finished stream's whole motion as BVH, glb, npz or a frames message (after :meth:`end`)."""
        if self.result_url is None:
            raise ParameterError("result: the stream has not ended, or it sent no frames")
        with urllib.request.urlopen(http_url(self.url, self.result_url) + "?" + urlencode({"format": format}),
                                    timeout=self.timeout_s) as r:
            return r.read()

    def _recv(self, timeout_s: float):
        from websockets.exceptions import ConnectionClosed

        try:
            return self._ws.recv(timeout=timeout_s)
        except TimeoutError:
            return None
        except ConnectionClosed as exc:
            if self.done is not None:
                return None
            rcvd = exc.rcvd
            raise LiveError("closed", f"the server closed the stream (code {getattr(rcvd, 'code', None)}, "
                                      f"{getattr(rcvd, 'reason', '')!r})") from None

    def _handle(self, msg, out: list) -> None:
        if isinstance(msg, bytes):
            m = P.unpack_frames(msg)
            out.append(Frames(m.start, m.root_positions, m.rotations, m.steps, m.samples))
            return
        m = json.loads(msg)
        kind = m.get("type")
        if kind == "ready":
            self.ready = m
        elif kind == "error":
            if m.get("fatal"):
                raise LiveError(m.get("code", "error"), m.get("message", ""))
            self.errors.append(m)
        elif kind == "done":
            self.done, self.result_url = m, m.get("result")
        else:
            self.events.append(m)


def synthesize_file(server: str, audio, *, format: str = "bvh", transcript=None, control: str | None = None,
                    seed: int = 0, timeout_s: float = 600.0) -> bytes:
    """``POST /synth``: the offline result for a WAV, as the bytes of a BVH, glb, npz, JSON or frames message.

    Parameters
    ----------
    server : str
        ``http://HOST:PORT``.
    audio : path or bytes
        A WAV file (read here; the server never sees the path).
    transcript : path, optional
        Word timings (.TextGrid, .tsv or .json), sent as a file.

    Raises
    ------
    GestureDBError
        The server's message when it refuses the request.
    """
    wav = audio if isinstance(audio, (bytes, bytearray)) else open(os.fspath(audio), "rb").read()
    query = urlencode({k: v for k, v in {"format": format, "control": control, "seed": seed}.items() if v is not None})
    fields = [("audio", "speech.wav", "audio/wav", bytes(wav))]
    if transcript is not None:
        with open(os.fspath(transcript), "rb") as f:
            fields.append(("transcript", os.path.basename(os.fspath(transcript)), "text/plain", f.read()))
    boundary = secrets.token_hex(16)
    body = b"".join(
        f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; filename="{fname}"\r\n'
        f"Content-Type: {ctype}\r\n\r\n".encode() + data + b"\r\n" for name, fname, ctype, data in fields
    ) + f"--{boundary}--\r\n".encode()
    req = urllib.request.Request(server.rstrip("/") + "/synth?" + query, data=body, method="POST",
                                 headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as r:
            return r.read()
    except urllib.error.HTTPError as exc:
        try:
            detail = json.loads(exc.read()).get("message", "")
        except ValueError:
            detail = ""
        raise GestureDBError(f"POST /synth: HTTP {exc.code}: {detail}") from None
