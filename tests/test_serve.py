"""gesturedb serve: the HTTP endpoints, the WebSocket protocol, its limits and isolation between clients.

The WebSocket path is tested against tests/serve_double.ReplayStream (the agreed
Stream interface, replaying database frames) so that it does not wait on the
streaming synthesizer; the tests marked `real_stream` run the same path on
gesturedb.synth.stream.Stream where it exists. Offline synthesis (POST /synth) is
the real Searcher on the real recording.
"""
from __future__ import annotations

import io
import json
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")

from starlette.testclient import TestClient  # noqa: E402
from starlette.websockets import WebSocketDisconnect  # noqa: E402

import gesturedb  # noqa: E402
from gesturedb.errors import GestureDBError, ParameterError  # noqa: E402
from gesturedb.serve import Limits, create_app  # noqa: E402
from gesturedb.serve import protocol as P  # noqa: E402
from gesturedb.serve.client import LiveClient, LiveError, synthesize_file  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from serve_double import ReplayStream  # noqa: E402

SR = 16000


def _real_stream():
    try:
        from gesturedb.synth.stream import Stream
    except ImportError:
        return None
    return Stream


real_stream = pytest.mark.skipif(_real_stream() is None, reason="gesturedb.synth.stream is not there yet")


@pytest.fixture(scope="module")
def db(scott_db_path):
    with gesturedb.open(scott_db_path) as d:
        yield d


@pytest.fixture(scope="module")
def speech(scott_dir):
    from gesturedb.io import read_audio

    x, sr = read_audio(scott_dir / "2_scott_0_1_1.wav", sr=SR)
    assert sr == SR
    return x


@pytest.fixture()
def client(db):
    with TestClient(create_app(db, stream_factory=ReplayStream)) as c:
        yield c


def _start(ws, **kw):
    ws.send_text(json.dumps({"type": "start", "sample_rate": SR, "format": "pcm16", **kw}))
    return ws.receive_json()


def _closed_with(ws, code: int, error: str):
    """The stream sends an error message with this code, then closes with this close code."""
    m = ws.receive_json()
    assert m["type"] == "error" and m["code"] == error and m["fatal"], m
    with pytest.raises(WebSocketDisconnect) as e:
        ws.receive_text()
    assert e.value.code == code
    return m


# -- the wire format ------------------------------------------------------------
def test_frames_layout_round_trip():
    rng = np.random.default_rng(0)
    for count, J in [(0, 3), (1, 1), (7, 55)]:
        root = rng.normal(size=(count, 3)).astype(np.float32)
        rot = rng.normal(size=(count, J, 4)).astype(np.float32)
        msg = P.pack_frames(12, root, rot, [{"a": float("nan"), "b": np.int64(3)}] if count else [])
        start, r, q, steps, samples = P.unpack_frames(msg)
        assert samples == 0 and start == 12 and np.array_equal(r, root) and np.array_equal(q, rot)
        assert steps == ([{"a": None, "b": 3}] if count else [])
    with pytest.raises(ParameterError, match="magic"):
        P.unpack_frames(b"XXXX" + bytes(24))
    with pytest.raises(ParameterError, match="header says"):
        P.unpack_frames(P.pack_frames(0, np.zeros((2, 3)), np.zeros((2, 2, 4)))[:-4])


def test_audio_decoding_checks():
    x = np.array([0.5, -0.25, 1.5], np.float32)
    assert np.allclose(P.decode_audio(P.encode_audio(x, "pcm16"), "pcm16"), [0.5, -0.25, 1.0], atol=1e-4)
    assert np.array_equal(P.decode_audio(P.encode_audio(x, "f32"), "f32"), [0.5, -0.25, 1.0])
    with pytest.raises(ParameterError, match="whole number of pcm16 samples"):
        P.decode_audio(b"abc", "pcm16")
    with pytest.raises(ParameterError, match="whole number of pcm16 samples"):
        P.audio_samples(b"abc", "pcm16")
    with pytest.raises(ParameterError, match="finite f32 samples; got 1 NaN"):
        P.audio_samples(np.array([np.nan, 0], "<f4").tobytes(), "f32")
    assert P.audio_samples(P.encode_audio(x, "pcm16"), "pcm16") == P.audio_samples(P.encode_audio(x, "f32"), "f32") == 3
    with pytest.raises(ParameterError, match="finite f32"):
        P.decode_audio(np.array([np.nan, 0], "<f4").tobytes(), "f32")


def test_limits_checked():
    with pytest.raises(ParameterError, match="Limits.idle_s"):
        Limits(idle_s=0)
    with pytest.raises(ParameterError, match="Limits.max_streams"):
        Limits(max_streams=1.5)


def test_step_latency_summary_is_numpys_percentiles_of_the_latest_steps():
    from gesturedb.serve.app import StepLatency

    lat = StepLatency(keep=50)
    assert lat.summary() == {"steps": 0, "over": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
    x = np.linspace(0.001, 0.1, 60)
    for v in x[:-2]:
        lat.add(v)
    lat.add(x[-2], steps=2)  # one chunk completing two steps: both timed from the same message
    kept = np.append(x[:-2], [x[-2], x[-2]])[-50:]
    got = lat.summary()
    assert got["steps"] == 60 and got["over"] == 50 and got["max_ms"] == pytest.approx(kept.max() * 1000)
    assert got["p99_ms"] == pytest.approx(np.percentile(kept, 99) * 1000)
    assert lat.summary(last=10)["p50_ms"] == pytest.approx(np.percentile(kept[-10:], 50) * 1000)


# -- HTTP -----------------------------------------------------------------------
def test_health_skeleton_controls(client, db):
    h = client.get("/health").json()
    assert h["status"] == "ok" and h["frames"] == db.n_frames and h["stream"] is True
    assert set(h["step_latency"]) == {"steps", "over", "p50_ms", "p99_ms", "max_ms"}
    bad = client.get("/health", params={"last": "-3"})
    assert bad.status_code == 400 and bad.json()["message"] == "last: expected a number of steps >= 1; got '-3'"
    sk = client.get("/skeleton").json()
    assert sk["names"] == db.skeleton.names and sk["parents"] == db.skeleton.parents.tolist()
    assert np.allclose(sk["offsets"], db.skeleton.offsets, atol=1e-6) and sk["frame_floats"] == 3 + 4 * len(sk["names"])
    c = client.get("/controls").json()
    assert {x["name"] for x in c["controls"]} == set(db.control_datasets)
    assert {x["name"] for x in c["masks"]} == set(db.mask_datasets)


def test_studio_page_and_three_js(client):
    r = client.get("/")
    assert r.status_code == 200 and "<canvas" in r.text or "studio.js" in r.text
    assert client.get("/studio/studio.js").status_code == 200
    assert client.get("/studio/capture-worklet.js").status_code == 200
    three = client.get("/vendor/three.module.js")
    if client.get("/health").json()["three_js"]:
        assert three.status_code == 200 and "REVISION" in three.text
    else:
        assert three.status_code == 404 and "libjs-three" in three.text


def test_source_stretch_is_the_database_motion(client, db):
    rec = db.recordings[0].name
    r = client.get("/source", params={"recording": rec, "start_s": 1, "end_s": 3})
    start, root, rot, _, _ = P.unpack_frames(r.content)
    m = db.motion(rec, 1, 3)
    assert start == 0 and np.array_equal(root, m.root_positions.astype(np.float32))
    assert np.array_equal(rot, m.rotations.astype(np.float32))
    bad = client.get("/source", params={"recording": "../../etc/passwd", "start_s": 0, "end_s": 1})
    assert bad.status_code == 400 and "recording" in bad.json()["message"]
    assert client.get("/source", params={"recording": rec, "start_s": 0, "end_s": 1e9}).status_code == 400


def _wav_bytes(x, sr=SR) -> bytes:
    import soundfile as sf

    buf = io.BytesIO()
    sf.write(buf, x, sr, format="WAV", subtype="PCM_16")
    return buf.getvalue()


@pytest.mark.slow
def test_offline_synth_matches_the_searcher(client, db, speech, scott_dir):
    """POST /synth gives what Searcher.synthesize gives for the same WAV, in every format."""
    from gesturedb.io import read_bvh
    from gesturedb.synth import Searcher

    wav = _wav_bytes(speech[: 6 * SR])
    files = {"audio": ("x.wav", wav, "audio/wav")}
    r = client.post("/synth", params={"format": "npz", "control": "left_wrist_height_high"}, files=files)
    assert r.status_code == 200, r.text
    got = np.load(io.BytesIO(r.content))
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        p = os.path.join(tmp, "s.wav")
        open(p, "wb").write(wav)
        want = Searcher(db).synthesize(p, control="left_wrist_height_high")
    assert np.array_equal(got["rotations"], want.motion.rotations.astype(np.float32))
    assert np.array_equal(got["root_positions"], want.motion.root_positions.astype(np.float32))
    prov = client.post("/synth", params={"format": "json", "control": "left_wrist_height_high"}, files=files).json()
    assert [s["db_frame"] for s in prov["steps"]] == [s["db_frame"] for s in want.steps]
    assert {s["control"] for s in prov["steps"]} == {"left_wrist_height_high"}
    bvh = client.post("/synth", params={"format": "bvh"}, content=wav, headers={"content-type": "audio/wav"})
    assert bvh.status_code == 200 and bvh.headers["content-disposition"].endswith('gesturedb.bvh"')
    with tempfile.TemporaryDirectory() as tmp:
        open(os.path.join(tmp, "r.bvh"), "wb").write(bvh.content)
        assert read_bvh(os.path.join(tmp, "r.bvh")).rotations.shape[0] == want.n_frames
    glb = client.post("/synth", params={"format": "glb"}, files=files)
    assert glb.status_code == 200 and glb.content[:4] == b"glTF"
    # a transcript travels as a file; its name gives only the format
    tg = (scott_dir / "2_scott_0_1_1.TextGrid").read_bytes()
    r = client.post("/synth", params={"format": "json"},
                    files={"audio": ("x.wav", _wav_bytes(speech), "audio/wav"), "transcript": ("/etc/w.TextGrid", tg)})
    assert r.status_code == 200, r.text


def test_offline_synth_refuses_bad_input(client):
    r = client.post("/synth", content=b"RIFF not really a wav" * 10, headers={"content-type": "audio/wav"})
    assert r.status_code == 400 and r.json()["error"] == "bad_input"
    assert "/tmp" not in r.json()["message"] and "gesturedb-serve-" not in r.json()["message"]
    r = client.post("/synth", params={"format": "exe"}, content=b"x", headers={"content-type": "audio/wav"})
    assert r.status_code == 400 and "format: expected one of bvh" in r.json()["message"]
    r = client.post("/synth", params={"control": "nonsense > p3"}, content=b"x", headers={"content-type": "audio/wav"})
    assert r.status_code == 400 and "unknown control feature 'nonsense'" in r.json()["message"]
    r = client.post("/synth", content=b"x", headers={"content-type": "text/plain"})
    assert r.status_code == 415
    r = client.post("/synth", files={"audio": ("x.wav", b"x"), "transcript": ("w.exe", b"x")})
    assert r.status_code == 400 and "TextGrid" in r.json()["message"]
    r = client.post("/synth", headers={"origin": "http://evil.example"}, content=b"x")
    assert r.status_code == 403


def test_upload_limit(db):
    with TestClient(create_app(db, stream_factory=ReplayStream, limits=Limits(max_upload_bytes=1000))) as c:
        r = c.post("/synth", content=bytes(5000), headers={"content-type": "audio/wav"})
        assert r.status_code == 413 and "limit is 1000 bytes" in r.json()["message"]

        def chunks():  # no Content-Length: counted as it arrives
            for _ in range(10):
                yield bytes(500)

        r = c.post("/synth", content=chunks(), headers={"content-type": "audio/wav"})
        assert r.status_code == 413 and "over the limit of 1000 bytes" in r.json()["message"]


# -- the WebSocket stream, in process ----------------------------------------------
def test_stream_round_trip(client, db, speech):
    x = speech[: 5 * SR]
    got = []
    timed_before = client.get("/health").json()["step_latency"]["steps"]
    with client.websocket_connect("/stream") as ws:
        ready = _start(ws, control="left_wrist_height_high")
        assert ready["type"] == "ready" and ready["fps"] == db.fps and ready["joints"] == db.skeleton.n_joints
        a = 0
        for n in [1, 333, 16000, 7, 20000, 1000]:  # any chunk size
            ws.send_bytes(P.encode_audio(x[a:a + n]))
            a += n
        ws.send_bytes(P.encode_audio(x[a:]))
        ws.send_text(json.dumps({"type": "end"}))
        while True:
            m = ws.receive()
            if m.get("bytes") is not None:
                got.append(P.unpack_frames(m["bytes"]))
                continue
            done = json.loads(m["text"])
            if done["type"] == "done":
                break
    starts = [g[0] for g in got]
    counts = [g[1].shape[0] for g in got]
    assert starts == list(np.cumsum([0] + counts[:-1]))  # contiguous, in order
    total = sum(counts)
    assert done["frames"] == total == int(np.ceil(x.shape[0] / SR * db.fps))
    steps = [s for g in got for s in g[3]]
    assert [s["out_start"] for s in steps] == list(range(0, total, 8))
    assert {s["control"] for s in steps} == {"left_wrist_height_high"}
    # the server timed every step that an audio message completed (the last ones come with the end message)
    timed = client.get("/health").json()["step_latency"]["steps"] - timed_before
    assert 0 < timed <= len(steps)
    lat = client.get("/health", params={"last": timed}).json()["step_latency"]
    assert lat["over"] == timed and 0 <= lat["p50_ms"] <= lat["p99_ms"] <= lat["max_ms"] < 60_000
    # the whole result downloads as what was streamed
    npz = np.load(io.BytesIO(client.get(done["result"], params={"format": "npz"}).content))
    assert np.array_equal(npz["rotations"], np.concatenate([g[2] for g in got]))
    assert client.get(done["result"], params={"format": "bvh"}).text.startswith("HIERARCHY")
    assert client.get(done["result"], params={"format": "glb"}).content[:4] == b"glTF"
    assert client.get("/result/" + "0" * 32).status_code == 404
    assert client.get("/result/..%2F..%2Fetc").status_code == 404


def test_control_switches_from_the_next_step(client, speech):
    with client.websocket_connect("/stream") as ws:
        _start(ws, total_samples=4 * SR)  # a factory without n_samples: the length told is not passed on
        ws.send_bytes(P.encode_audio(speech[: 2 * SR]))
        first = P.unpack_frames(ws.receive_bytes())
        ws.send_text(json.dumps({"type": "control", "control": "right_wrist_speed_low"}))
        ack = ws.receive_json()
        assert ack == {"type": "control", "control": "right_wrist_speed_low", "from_frame": len(first[1])}
        ws.send_bytes(P.encode_audio(speech[2 * SR: 4 * SR]))
        later = P.unpack_frames(ws.receive_bytes())
    assert {s["control"] for s in first[3]} == {None}
    assert {s["control"] for s in later[3]} == {"right_wrist_speed_low"}


def test_control_schedules_are_checked_item_by_item(client):
    with client.websocket_connect("/stream") as ws:
        _start(ws, control="0-2: left_wrist_height_high; 2-: hand_speed_low")
        ws.send_text(json.dumps({"type": "control", "control": "0-1: left_wrist_height_high; 1-: nope_low"}))
        m = ws.receive_json()
        assert m["code"] == "bad_control" and "nope_low" in m["message"] and not m["fatal"]
        ws.send_text(json.dumps({"type": "control", "control": "0-1: x > p5; 0-2: y < p3"}))
        assert ws.receive_json()["code"] == "bad_control"


@pytest.mark.parametrize("first, code, error", [
    (b"\x00\xff garbage", P.CLOSE_POLICY, "bad_message"),
    ("not json {", P.CLOSE_POLICY, "bad_message"),
    (json.dumps({"type": "control"}), P.CLOSE_POLICY, "bad_message"),
    (json.dumps({"type": "start", "sample_rate": 7}), P.CLOSE_POLICY, "bad_rate"),
    (json.dumps({"type": "start", "sample_rate": 16000.5}), P.CLOSE_POLICY, "bad_rate"),
    (json.dumps({"type": "start", "sample_rate": 16000, "format": "mp3"}), P.CLOSE_POLICY, "bad_format"),
    (json.dumps({"type": "start", "sample_rate": 16000, "control": "no_such_mask"}), P.CLOSE_POLICY, "bad_control"),
    (json.dumps({"type": "start", "sample_rate": 16000, "protocol": 99}), P.CLOSE_POLICY, "bad_protocol"),
    (json.dumps({"type": "start", "sample_rate": 16000, "total_samples": -1}), P.CLOSE_POLICY, "bad_start"),
    (json.dumps({"type": "start", "sample_rate": 16000, "total_samples": "16000"}), P.CLOSE_POLICY, "bad_start"),
    (json.dumps({"type": "start", "sample_rate": 16000, "total_samples": True}), P.CLOSE_POLICY, "bad_start"),
    (json.dumps({"type": "start", "sample_rate": 16000, "total_samples": 10**12}), P.CLOSE_POLICY, "bad_start"),
])
def test_bad_start_is_an_error_message_then_a_close(client, first, code, error):
    with client.websocket_connect("/stream") as ws:
        ws.send_bytes(first) if isinstance(first, bytes) else ws.send_text(first)
        m = _closed_with(ws, code, error)
    assert m["message"]


def test_bad_messages_mid_stream_are_refused_and_the_stream_goes_on(client, speech):
    with client.websocket_connect("/stream") as ws:
        _start(ws, format="f32")
        for bad, code in [(b"abc", "bad_audio"), (np.array([np.nan] * 4, "<f4").tobytes(), "bad_audio"),
                          ("{{{", "bad_message"), (json.dumps([1, 2]), "bad_message"),
                          (json.dumps({"type": "dance"}), "bad_message"),
                          (json.dumps({"type": "control", "control": "left_wrist_height > p101"}), "bad_control"),
                          (json.dumps({"type": "control", "control": 5}), "bad_control"),
                          (json.dumps({"type": "words", "words": [[2, 1, "x"]]}), "bad_words")]:
            ws.send_bytes(bad) if isinstance(bad, bytes) else ws.send_text(bad)
            m = ws.receive_json()
            assert m["type"] == "error" and m["code"] == code and not m["fatal"], m
        ws.send_text(json.dumps({"type": "words", "words": [[0.1, 0.4, "hello"]]}))
        ws.send_bytes(P.encode_audio(speech[: 2 * SR], "f32"))
        start, root, rot, steps, samples = P.unpack_frames(ws.receive_bytes())
        assert samples == 2 * SR and start == 0 and root.shape[0] > 0 and {s["control"] for s in steps} == {None}


def test_too_many_errors_close_the_stream(db):
    with TestClient(create_app(db, stream_factory=ReplayStream, limits=Limits(max_errors=3))) as c:
        with c.websocket_connect("/stream") as ws:
            _start(ws)
            for _ in range(3):
                ws.send_bytes(b"x")
                assert ws.receive_json()["fatal"] is False
            ws.send_bytes(b"x")
            _closed_with(ws, P.CLOSE_POLICY, "too_many_errors")


def test_message_size_and_idle_limits(db):
    lim = Limits(max_message_bytes=4096, idle_s=0.3)
    with TestClient(create_app(db, stream_factory=ReplayStream, limits=lim)) as c:
        with c.websocket_connect("/stream") as ws:
            _start(ws)
            ws.send_bytes(bytes(4097))
            m = _closed_with(ws, P.CLOSE_TOO_BIG, "too_big")
            assert "limit is 4096 bytes" in m["message"]
        with c.websocket_connect("/stream") as ws:
            _start(ws)
            t = time.monotonic()
            _closed_with(ws, P.CLOSE_POLICY, "idle")
            assert time.monotonic() - t < 5
        with c.websocket_connect("/stream") as ws:  # silent before the start message too
            _closed_with(ws, P.CLOSE_POLICY, "idle")


class _SlowControl(ReplayStream):
    def set_control(self, control):
        time.sleep(0.6)
        super().set_control(control)


def test_idle_limit_counts_only_the_wait_for_a_message(db):
    """The idle limit is one timer per session (not a timeout per message): messages that come more often
    keep the stream open however long it lasts, and a slow synthesizer call is no idleness of the client."""
    lim = Limits(idle_s=0.3)
    with TestClient(create_app(db, stream_factory=_SlowControl, limits=lim)) as c:
        with c.websocket_connect("/stream") as ws:
            _start(ws)
            t = time.monotonic()
            while time.monotonic() - t < 1.0:  # three times the limit, a message every 0.1 s
                ws.send_text(json.dumps({"type": "ping"}))
                assert ws.receive_json()["type"] == "pong"
                time.sleep(0.1)
            ws.send_text(json.dumps({"type": "control", "control": None}))  # 0.6 s in the synthesizer
            assert ws.receive_json()["type"] == "control"
            ws.send_text(json.dumps({"type": "ping"}))
            assert ws.receive_json()["type"] == "pong"
            t = time.monotonic()
            m = _closed_with(ws, P.CLOSE_POLICY, "idle")
            assert "no message for 0.3 s" in m["message"] and 0.2 < time.monotonic() - t < 5


def test_audio_faster_than_real_time_is_slowed(db, speech):
    """A client that feeds audio at full speed gets real time once past the allowance."""
    with TestClient(create_app(db, stream_factory=ReplayStream, limits=Limits(max_ahead_s=0.5))) as c:
        with c.websocket_connect("/stream") as ws:
            _start(ws)
            t = time.monotonic()
            for k in range(4):
                ws.send_bytes(P.encode_audio(speech[k * SR // 2:(k + 1) * SR // 2]))
            ws.send_text(json.dumps({"type": "ping"}))
            while ws.receive().get("text") is None:
                pass
            assert time.monotonic() - t >= 2.0 - 0.5 - 0.1  # 2 s of speech, 0.5 s ahead allowed


def test_too_much_audio_closes_the_stream(db):
    with TestClient(create_app(db, stream_factory=ReplayStream, limits=Limits(max_audio_s=1.0))) as c:
        with c.websocket_connect("/stream") as ws:
            _start(ws)
            ws.send_bytes(P.encode_audio(np.zeros(SR // 2)))
            ws.send_bytes(P.encode_audio(np.zeros(SR)))
            _closed_with(ws, P.CLOSE_POLICY, "too_long")


def test_stream_limit_and_foreign_origin(db):
    with TestClient(create_app(db, stream_factory=ReplayStream, limits=Limits(max_streams=2))) as c:
        with c.websocket_connect("/stream") as a, c.websocket_connect("/stream") as b:
            _start(a), _start(b)
            with c.websocket_connect("/stream") as third:
                _closed_with(third, P.CLOSE_TRY_LATER, "busy")
        with c.websocket_connect("/stream") as again:  # the two are gone: room again
            assert _start(again)["type"] == "ready"
        with pytest.raises(WebSocketDisconnect) as e:
            with c.websocket_connect("/stream", headers={"origin": "http://evil.example"}) as ws:
                ws.receive_text()
        assert e.value.code == P.CLOSE_POLICY


def test_synthesizer_failure_ends_only_that_stream(db, speech):
    class Broken(ReplayStream):
        def push(self, samples):
            raise RuntimeError("boom")

    made = []

    def factory(d, *, sample_rate):
        made.append(None)
        return (Broken if len(made) == 2 else ReplayStream)(d, sample_rate=sample_rate)

    with TestClient(create_app(db, stream_factory=factory)) as c:  # made[0]: the server's warm-up stream
        with c.websocket_connect("/stream") as bad, c.websocket_connect("/stream") as good:
            _start(bad), _start(good)
            bad.send_bytes(P.encode_audio(speech[:SR]))
            m = _closed_with(bad, P.CLOSE_INTERNAL, "internal")
            assert "RuntimeError: boom" in m["message"]
            good.send_bytes(P.encode_audio(speech[: 2 * SR]))
            assert P.unpack_frames(good.receive_bytes())[1].shape[0] > 0


def test_no_stream_is_said_not_dropped(db, monkeypatch):
    import gesturedb.serve.app as appmod

    monkeypatch.setattr(appmod, "default_stream_factory", lambda: (None, "live streaming is not available: test"))
    with TestClient(create_app(db)) as c:
        assert c.get("/health").json()["stream"] is False
        with c.websocket_connect("/stream") as ws:
            ws.send_text(json.dumps({"type": "start", "sample_rate": SR}))
            m = _closed_with(ws, P.CLOSE_INTERNAL, "unavailable")
            assert "not available" in m["message"]


# -- a real server: uvicorn on a port --------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LiveServer:
    """uvicorn serving the app in a thread of this process, as `gesturedb serve` runs it."""

    def __init__(self, app, limits: Limits, **options):
        """options: uvicorn.Config's, over those of `gesturedb serve`."""
        import uvicorn

        from gesturedb.serve.websocket import uvicorn_options

        self.port = _free_port()
        cfg = uvicorn.Config(app, host="127.0.0.1", port=self.port, log_level="warning",
                             **{**uvicorn_options(limits), **options})
        self.server = uvicorn.Server(cfg)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self):
        self.thread.start()
        for _ in range(200):
            if self.server.started:
                return self
            time.sleep(0.05)
        raise RuntimeError("uvicorn did not start")

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(10)

    @property
    def ws(self) -> str:
        return f"ws://127.0.0.1:{self.port}/stream"

    @property
    def http(self) -> str:
        return f"http://127.0.0.1:{self.port}"


def _stream_all(url, x, *, chunk=SR // 10, realtime=False, control=None, fmt="pcm16"):
    """Stream x through LiveClient; the frames in order (root, rotations), the steps and per-chunk timing."""
    frames = []
    with LiveClient(url, sample_rate=SR, format=fmt, control=control) as live:
        t0 = time.monotonic()
        for a in range(0, x.shape[0], chunk):
            live.send_audio(x[a:a + chunk])
            if realtime:
                time.sleep(max(0.0, t0 + (a + chunk) / SR - time.monotonic()))
            frames += live.poll()
        frames += live.end()
        result = live.result("npz")
    root = np.concatenate([f.root_positions for f in frames if len(f)])
    rot = np.concatenate([f.rotations for f in frames if len(f)])
    return root, rot, [s for f in frames for s in f.steps], result


@pytest.fixture(scope="module")
def live(db):
    lim = Limits(max_message_bytes=1 << 20)
    with LiveServer(create_app(db, stream_factory=ReplayStream, limits=lim), lim) as s:
        yield s


def test_python_client_streams_and_downloads(live, speech):
    root, rot, steps, result = _stream_all(live.ws, speech[: 4 * SR], fmt="f32")
    assert rot.shape == (60, 55, 4) and len(steps) == 8
    npz = np.load(io.BytesIO(result))
    assert np.array_equal(npz["rotations"], rot)
    with LiveClient(live.ws) as c:
        assert c.skeleton()["names"][0] == "pelvis"
        c.set_control("no_such_mask")  # refused, the stream goes on
        c.send_audio(speech[: 2 * SR])
        got = []
        for _ in range(10):
            got += c.poll(2.0)
            if got:
                break
        assert sum(len(f) for f in got) > 0 and c.errors[0]["code"] == "bad_control"
    with pytest.raises(LiveError, match="bad_rate"):
        LiveClient(live.ws, sample_rate=1).connect()


def test_python_client_offline(live, speech):
    prov = json.loads(synthesize_file(live.http, _wav_bytes(speech[: 3 * SR]), format="json"))
    assert prov["n_frames"] == 45
    with pytest.raises(GestureDBError, match="HTTP 400: .*format"):
        synthesize_file(live.http, b"x", format="mp4")


def test_garbage_client_does_not_disturb_another(live, speech):
    """Two clients at once; one sends garbage, a 100 MB message, hangs up mid-stream: the other's frames are
    exactly what it gets alone."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    x = speech[: 6 * SR]
    alone = _stream_all(live.ws, x)
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("r", _stream_all(live.ws, x, realtime=True, chunk=SR // 5)))
    t.start()
    codes = []
    for first in [b"\xde\xad\xbe\xef" * 1000, "{\"type\": \"start\", \"sample_rate\": -1}", bytes(100 << 20)]:
        with connect(live.ws, max_size=None) as ws:
            try:
                ws.send(first)
                while True:
                    ws.recv(timeout=10)
            except ConnectionClosed as exc:
                codes.append(exc.rcvd.code)
    with connect(live.ws) as ws:  # starts, then leaves without a word mid-stream
        ws.send(json.dumps({"type": "start", "sample_rate": SR}))
        ws.recv(timeout=10)
        ws.send(P.encode_audio(x[:SR]))
    t.join(60)
    assert codes == [P.CLOSE_POLICY, P.CLOSE_POLICY, P.CLOSE_TOO_BIG]
    root, rot, steps, _ = out["r"]
    assert np.array_equal(rot, alone[1]) and np.array_equal(root, alone[0]) and steps == alone[2]


def _send_oversize(url: str, compression: str | None):
    """Send 100 MB of zeros (about 100 kB deflated) as one message; what the server closed with, the
    negotiated extensions."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with connect(url, max_size=None, compression=compression) as ws:
        extensions = [e.name for e in ws.protocol.extensions]
        with pytest.raises(ConnectionClosed) as e:
            ws.send(bytes(100 << 20))
            ws.recv(timeout=30)
    assert e.value.rcvd is not None, f"expected close {P.CLOSE_TOO_BIG} with a reason; got a dropped socket: {e.value!r}"
    return e.value.rcvd, extensions


@pytest.mark.parametrize("deflate", [False, True], ids=["plain", "deflate"])
def test_oversize_message_is_refused_with_a_reason(db, deflate):
    """A message over the WebSocket layer's limit gets close 1009 and why, whether it came deflated or not
    (`gesturedb serve` declines deflate; uvicorn's default, here too, takes it).
    A peer that never closes is dropped after the linger; the next client is served. The race of the close frame with a reset is checked in
    test_cli_serve_binds_localhost: with client and server in one process it did not show."""
    from websockets.sync.client import connect

    from gesturedb.serve.websocket import LINGER_S

    lim = Limits(max_message_bytes=1 << 16)
    app = create_app(db, stream_factory=ReplayStream, limits=lim)
    with LiveServer(app, lim, ws_per_message_deflate=deflate) as srv:
        for _ in range(2):
            close, extensions = _send_oversize(srv.ws, "deflate" if deflate else None)
            assert close.code == P.CLOSE_TOO_BIG and f"limit of {lim.ws_max_size} bytes" in close.reason, close
            assert extensions == (["permessage-deflate"] if deflate else [])
        with socket.create_connection(("127.0.0.1", srv.port)) as s:  # a peer that sends on and never closes
            s.sendall(b"GET /stream HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                      b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n")
            assert s.recv(4096).startswith(b"HTTP/1.1 101")
            s.sendall(b"\x82\xff" + (100 << 20).to_bytes(8, "big") + bytes(4 + (1 << 20)))  # masked, 100 MB
            assert s.recv(2)[0] == 0x88  # the close frame, then (below) the server's half of the socket goes
            t = time.monotonic()
            while srv.server.server_state.connections and time.monotonic() - t < LINGER_S + 5:
                time.sleep(0.05)
            assert not srv.server.server_state.connections, f"still open {LINGER_S + 5:g} s after the close"
        with connect(srv.ws) as ws:
            ws.send(json.dumps({"type": "start", "sample_rate": SR}))
            assert json.loads(ws.recv(timeout=10))["type"] == "ready"


def test_many_connections_at_once(db, speech):
    """More connections than streams allowed, all at once: the extra ones are told to come back, the others
    stream, and once they are gone a new client is served."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    lim = Limits(max_streams=16)
    with LiveServer(create_app(db, stream_factory=ReplayStream, limits=lim), lim) as srv:
        outcome = []
        lock = threading.Lock()
        barrier = threading.Barrier(40)

        def one():
            with connect(srv.ws) as ws:
                barrier.wait(30)
                try:
                    ws.send(json.dumps({"type": "start", "sample_rate": SR}))
                    m = json.loads(ws.recv(timeout=30))
                    if m["type"] == "ready":
                        barrier.wait(30)  # hold the stream until every connection has its answer
                        ws.send(P.encode_audio(speech[: 2 * SR]))
                        P.unpack_frames(ws.recv(timeout=30))
                        r = "served"
                    else:
                        r = m["code"]
                        barrier.wait(30)
                except ConnectionClosed as exc:  # told before it could send its start
                    r = "busy" if exc.rcvd.code == P.CLOSE_TRY_LATER else f"closed {exc.rcvd.code}"
                    barrier.wait(30)
            with lock:
                outcome.append(r)

        threads = [threading.Thread(target=one) for _ in range(40)]
        [t.start() for t in threads]
        [t.join(60) for t in threads]
        assert sorted(outcome) == sorted(["served"] * 16 + ["busy"] * 24)
        root, rot, steps, _ = _stream_all(srv.ws, speech[: 2 * SR])
        assert rot.shape[0] == 30


def test_eight_concurrent_clients(live, speech):
    x = speech[: 4 * SR]
    alone = _stream_all(live.ws, x)
    res = [None] * 8

    def run(i):
        res[i] = _stream_all(live.ws, x, realtime=True, chunk=SR // 10)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(8)]
    [t.start() for t in threads]
    [t.join(60) for t in threads]
    for r in res:
        assert r is not None and np.array_equal(r[1], alone[1])
    assert json.loads(urllib.request.urlopen(live.http + "/health").read())["streams"] == 0


@real_stream
def test_real_stream_through_the_server_is_the_stream(db, speech):
    """The server passes the synthesizer's frames on unchanged: the same as Stream fed directly."""
    Stream = _real_stream()
    x = speech[: 8 * SR]
    s = Stream(db, sample_rate=SR)
    direct = []
    for a in range(0, x.shape[0], SR // 10):
        c = s.push(x[a:a + SR // 10])
        if c.motion is not None and c.motion.rotations.shape[0]:
            direct.append(c.motion.rotations.astype(np.float32))
    c = s.finish()
    if c.motion is not None and c.motion.rotations.shape[0]:
        direct.append(c.motion.rotations.astype(np.float32))
    lim = Limits()
    with LiveServer(create_app(db, limits=lim), lim) as srv:
        root, rot, steps, _ = _stream_all(srv.ws, x, fmt="f32")
    assert np.array_equal(rot, np.concatenate(direct))
    assert steps and all("recording" in st and "pose_rank" in st for st in steps)


@real_stream
@pytest.mark.slow
def test_eight_real_time_clients_no_frame_late(db, speech):
    """Eight clients stream speech in real time through the real Stream at once: every frame arrives
    within its latency (plus the client's 0.1 s chunks and a 0.15 s allowance for this shared machine)."""
    lim = Limits()
    chunk_s, allowance_s = 0.1, 0.15
    x = speech[: 8 * SR]
    late = [None] * 8

    def run(i):
        with LiveClient(srv.ws, sample_rate=SR) as live:
            arrivals = []
            t0 = time.monotonic()
            n = int(chunk_s * SR)
            for a in range(0, x.shape[0], n):
                time.sleep(max(0.0, t0 + a / SR - time.monotonic()))
                live.send_audio(x[a:a + n])
                for f in live.poll():
                    arrivals += [(f.start + k, time.monotonic()) for k in range(len(f))]
            deadline = live.latency_s + chunk_s + allowance_s
            late[i] = [round(t - t0 - (j / live.fps + deadline), 3) for j, t in arrivals if t - t0 > j / live.fps + deadline]
            live.end()

    with LiveServer(create_app(db, limits=lim), lim) as srv:
        threads = [threading.Thread(target=run, args=(i,)) for i in range(8)]
        [t.start() for t in threads]
        [t.join(120) for t in threads]
    assert all(v == [] for v in late), f"late frames (seconds past their deadline) per client: {late}"


# -- the command ---------------------------------------------------------------------
def test_cli_serve_binds_localhost(scott_db_path):
    port = _free_port()
    p = subprocess.Popen([sys.executable, "-m", "gesturedb.cli.main", "serve", str(scott_db_path), "--port", str(port)],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for _ in range(300):
            try:
                h = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=1).read())
                break
            except OSError:
                time.sleep(0.1)
        else:
            raise AssertionError("gesturedb serve did not answer")
        assert h["status"] == "ok" and h["database"] == "scott.h5"
        # a 100 MB message is refused by the WebSocket layer before it is read: the server's memory stays put
        def peak_kb():
            with open(f"/proc/{p.pid}/status") as f:
                return next(int(x.split()[1]) for x in f if x.startswith("VmHWM:"))

        before = peak_kb()
        # from a client without compression (as many engines' WebSocket libraries) and one offering it, which
        # the server declines: a reset overtook the close frame in 5 and 10 of 20 sends before the lingering close
        for compression in [None, "deflate"] * 4:
            close, extensions = _send_oversize(f"ws://127.0.0.1:{port}/stream", compression)
            assert close.code == P.CLOSE_TOO_BIG and extensions == [], (close, extensions)
        assert peak_kb() - before < 20_000, "the server's peak memory grew by the size of the refused message"
        assert json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=5).read())["status"] == "ok"
        with socket.socket() as s:  # bound to 127.0.0.1 only: the machine's other addresses do not answer
            addr = socket.gethostbyname(socket.gethostname())
            if not addr.startswith("127."):
                assert s.connect_ex((addr, port)) != 0
    finally:
        p.terminate()
        out = p.communicate(timeout=20)[0]
    assert f"http://127.0.0.1:{port}/" in out
