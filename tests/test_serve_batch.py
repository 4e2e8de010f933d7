"""gesturedb serve with many streams at once: their waiting steps are searched in one call
(gesturedb.serve.batcher), and each client still gets, bit for bit, the frames and provenance
its stream makes alone, whatever the other clients send or fail at (issue 39)."""
from __future__ import annotations

import json
import os
import sys
import threading

import numpy as np
import pytest

import gesturedb
from gesturedb.io import read_audio
from gesturedb.synth import SearchOptions

pytest.importorskip("uvicorn")
from websockets.exceptions import ConnectionClosed  # noqa: E402

from gesturedb.serve import Limits, create_app  # noqa: E402
from gesturedb.serve import protocol as P  # noqa: E402
from gesturedb.serve.client import LiveClient, LiveError  # noqa: E402
from gesturedb.synth.stream import Stream  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from test_serve import LiveServer  # noqa: E402

SR = 16000
CHUNK = 640  # 40 ms
CONTROLS = [None, "left_wrist_high", "0-6: symmetric; 6-: left_wrist_speed > p85", None, "left_wrist_high",
            "hand_speed_low"]


@pytest.fixture(scope="module")
def db(scott_db_path):
    with gesturedb.open(scott_db_path) as d:
        yield d


def _speech(scott_dir, j, seconds=12.0):
    wavs = sorted((scott_dir / "inputs").glob("*.wav"))
    x, sr = read_audio(wavs[j % len(wavs)], sr=SR)
    start = int((j // len(wavs)) * 7 * SR)  # the same file twice: another stretch of it
    return x[start:start + int(seconds * SR)]


def _alone(db, x, control):
    s = Stream(db, SearchOptions(control=control), sample_rate=SR)
    chunks = [s.push(x[a:a + CHUNK]) for a in range(0, x.shape[0], CHUNK)] + [s.finish()]
    rot = np.concatenate([c.motion.rotations for c in chunks]).astype(np.float32)
    root = np.concatenate([c.motion.root_positions for c in chunks]).astype(np.float32)
    steps = json.loads(json.dumps(P.json_safe([st for c in chunks for st in c.steps])))
    return root, rot, steps


def _fmt(j: int) -> str:
    """Every other client sends PCM16 (held as bytes by the server, decoded once per step), the others f32."""
    return "f32" if j % 2 == 0 else "pcm16"


def _client(url, x, control, out, j, total_samples=None):
    try:
        frames = []
        with LiveClient(url, sample_rate=SR, format=_fmt(j), control=control, total_samples=total_samples) as live:
            for a in range(0, x.shape[0], CHUNK):
                live.send_audio(x[a:a + CHUNK])
                frames += live.poll()
            frames += live.end()
        out[j] = (np.concatenate([f.root_positions for f in frames if len(f)]),
                  np.concatenate([f.rotations for f in frames if len(f)]), [s for f in frames for s in f.steps])
    except Exception as exc:  # noqa: BLE001 - reported by the test
        out[j] = exc


@pytest.mark.parametrize("ahead", [True, False], ids=["ahead", "batched"])
def test_concurrent_streams_through_the_batcher_are_each_alone_bit_for_bit(db, scott_dir, ahead):
    """With the coming steps pre-selected ahead of their speech (finished from that table) and without
    (every step in the batched search), each client gets what its stream makes alone."""
    speech = [_speech(scott_dir, j) for j in range(len(CONTROLS))]
    lim = Limits()
    app = create_app(db, limits=lim)
    sched = app.state.gesturedb.scheduler
    assert sched is not None
    sched.ahead_enabled = ahead
    out = [None] * len(CONTROLS)
    with LiveServer(app, lim) as srv:
        calls0, steps0 = sched.n_calls, sched.n_steps  # after the warm-up's batches
        used0, ahead_calls0 = sched.n_ahead_used, sched.n_ahead_calls
        threads = [threading.Thread(target=_client, args=(srv.ws, x, c, out, j))
                   for j, (x, c) in enumerate(zip(speech, CONTROLS))]
        [t.start() for t in threads]
        [t.join(300) for t in threads]
    for j, (x, c) in enumerate(zip(speech, CONTROLS)):
        assert not isinstance(out[j], BaseException) and out[j] is not None, (j, out[j])
        if _fmt(j) == "pcm16":  # alone: the samples the server decodes
            x = P.decode_audio(P.encode_audio(x, "pcm16"), "pcm16")
        root, rot, steps = _alone(db, x, c)
        assert np.array_equal(out[j][1], rot) and np.array_equal(out[j][0], root), j
        assert out[j][2] == steps, j
    # the steps went through the scheduler, several per call
    n_steps, n_used = sched.n_steps - steps0, sched.n_ahead_used - used0
    assert n_steps + n_used >= sum(len(o[2]) for o in out) - 2 * len(out)  # finish() runs the last steps itself
    if ahead:  # (a stale pre-selection or a guard without candidate takes the usual search)
        assert n_used >= 0.8 * (n_steps + n_used) and sched.n_ahead_calls - ahead_calls0 < n_used
        assert sched.n_ahead_stale == 0  # controls by schedule are known ahead
    else:
        assert n_used == 0 and sched.n_calls - calls0 < n_steps


def test_a_client_that_tells_its_length_has_its_last_step_preselected_too(db, scott_dir):
    """``total_samples`` in the start message: the stream's last, shorter step is pre-selected while its speech
    arrives like every other step, so none takes a pass over the database; without it the last step does. The
    frames are the stream's alone either way (one client at a time: the counts are its own)."""
    x = _speech(scott_dir, 1, 6.0)  # 90 frames: 11 full steps and a last one of 2 frames
    lim = Limits()
    app = create_app(db, limits=lim)
    sched = app.state.gesturedb.scheduler
    want = _alone(db, P.decode_audio(P.encode_audio(x, "pcm16"), "pcm16"), None)
    assert len(want[2]) == 12 and want[2][-1]["out_end"] - want[2][-1]["out_start"] == 2
    with LiveServer(app, lim) as srv:
        for told, usual in ((x.shape[0], 0), (None, 1)):
            steps0, used0 = sched.n_steps, sched.n_ahead_used
            out = [None, None]
            _client(srv.ws, x, None, out, 1, total_samples=told)
            out = out[1:]
            assert not isinstance(out[0], BaseException), out[0]
            assert np.array_equal(out[0][1], want[1]) and np.array_equal(out[0][0], want[0]) and out[0][2] == want[2]
            assert (sched.n_steps - steps0, sched.n_ahead_used - used0) == (usual, 12 - usual), told


def test_a_failing_stream_does_not_disturb_the_batch(db, scott_dir):
    """A client whose control leaves a step no candidate is closed with its own explained error; the
    clients batched with it get what they get alone."""
    bad = "left_wrist_height > p99 and left_wrist_height < p1"
    controls = [None, bad, "left_wrist_high"]
    speech = [_speech(scott_dir, j, 6.0) for j in range(3)]
    lim = Limits()
    out = [None] * 3
    with LiveServer(create_app(db, limits=lim), lim) as srv:
        threads = [threading.Thread(target=_client, args=(srv.ws, x, c, out, j))
                   for j, (x, c) in enumerate(zip(speech, controls))]
        [t.start() for t in threads]
        [t.join(300) for t in threads]
    # the error message, or (when the client was still sending) the close that follows it
    if isinstance(out[1], LiveError):
        assert out[1].code == "synthesis" and "no candidate" in str(out[1])
    else:
        assert isinstance(out[1], ConnectionClosed) and out[1].rcvd.code == P.CLOSE_POLICY
        assert out[1].rcvd.reason == "synthesis"
    for j in (0, 2):
        root, rot, steps = _alone(db, speech[j], controls[j])
        assert np.array_equal(out[j][1], rot) and out[j][2] == steps, j


def test_no_batch_serves_each_stream_alone(db, scott_dir):
    x = _speech(scott_dir, 0, 4.0)
    lim = Limits()
    app = create_app(db, limits=lim, batch_steps=False)
    assert app.state.gesturedb.scheduler is None
    out = [None]
    with LiveServer(app, lim) as srv:
        _client(srv.ws, x, None, out, 0)
    root, rot, steps = _alone(db, x, None)
    assert np.array_equal(out[0][1], rot) and out[0][2] == steps


def test_finish_ready_takes_only_a_done_and_fitting_preselection(db, scott_dir, monkeypatch):
    """StepScheduler.finish_ready (a session's worker thread, between feed and apply) finishes a step from a
    pre-selection that is done and still fits, bit for bit the step's own search; one under way is left to
    search() (which waits for it), a stale one is counted and searched as usual."""
    import asyncio

    from gesturedb.serve import batcher
    from gesturedb.serve.batcher import StepScheduler
    from gesturedb.synth import Searcher

    # a lone coming step waits this long for others before its pre-selection starts: "under way" below
    monkeypatch.setattr(batcher, "AHEAD_GATHER_S", 5.0)

    x = _speech(scott_dir, 0, 6.0)
    searcher = Searcher(db)
    sched = StepScheduler(searcher)
    s = searcher.stream(SearchOptions(), sample_rate=SR)

    def ready_step(fed):
        # feed until the next step is ready; (step, samples fed)
        while (sq := s.next_step()) is None:
            s.feed(x[fed:fed + CHUNK])
            fed += CHUNK
        return sq, fed

    async def run():
        sq, fed = ready_step(0)
        s.complete_step(sq, *s.search_step(sq))
        sched.ahead(s.upcoming_step())
        entry = sched._ahead[s]
        sq, fed = ready_step(fed)
        # under way (waiting for other steps): not taken, left for search()
        assert sched.finish_ready(sq) is None and sched._ahead[s] is entry
        with sched._cond:  # as search() does when a step's speech has come: start without waiting
            sched._ahead_now = True
            sched._ahead_cond.notify()
        await entry.fut
        got = sched.finish_ready(sq)
        alone = s.search_step(sq)
        assert got is not None and int(got[0].frames[0]) == int(alone[0].frames[0]) and got[1] == alone[1]
        assert sched.n_ahead_used == 1 and s not in sched._ahead
        s.complete_step(sq, *got)
        # a control set after the pre-selection: stale, counted, and the step is searched as usual
        sched.ahead(s.upcoming_step())
        with sched._cond:
            sched._ahead_now = True
            sched._ahead_cond.notify()
        await sched._ahead[s].fut
        s.set_control("left_wrist_high")
        sq, fed = ready_step(fed)
        assert sched.finish_ready(sq) is None
        assert sched.n_ahead_stale == 1 and sched.n_ahead_used == 1 and s not in sched._ahead

    asyncio.run(run())


def test_step_work_runs_in_one_thread_in_the_order_it_came(db):
    """StepScheduler.run_step: the sessions' step work runs in one thread, first come, first served (the
    steps of streams whose speech comes together go out one after the other, not all at the end of the
    burst), and a call's exception reaches its own caller only."""
    import asyncio
    import time

    from gesturedb.errors import GestureDBError
    from gesturedb.serve.batcher import StepScheduler
    from gesturedb.synth import Searcher

    sched = StepScheduler(Searcher(db))
    ran = []

    def work(i):
        time.sleep(0.002 * (i % 3))  # the later calls must not overtake a slower earlier one
        ran.append((i, threading.get_ident()))
        if i == 5:
            raise GestureDBError("step 5 has no candidate")
        return i * i

    async def run():
        calls = [asyncio.ensure_future(sched.run_step(work, i)) for i in range(12)]
        return await asyncio.gather(*calls, return_exceptions=True)

    got = asyncio.run(run())
    assert [i for i, _ in ran] == list(range(12))
    assert len({t for _, t in ran}) == 1 and ran[0][1] != threading.get_ident()
    assert isinstance(got[5], GestureDBError) and "step 5" in str(got[5])
    assert [g for i, g in enumerate(got) if i != 5] == [i * i for i in range(12) if i != 5]
