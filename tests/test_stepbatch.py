"""Many live streams' steps searched in one call (issue 39): each stream gets, bit for bit, the frames and
provenance it gets alone, on the real recording and inputs with different controls, options and guards."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError, SearchError
from gesturedb.io import read_audio
from gesturedb.synth import Searcher, SearchOptions
from gesturedb.synth.stepbatch import StepBatch

INPUTS = ["2_scott_0_2_2", "2_scott_0_3_3", "2_scott_0_4_4", "2_scott_0_5_5"]
OPTIONS = [
    SearchOptions(),
    SearchOptions(control="left_wrist_high", seed=5),
    SearchOptions(control="0-10: symmetric; 10-: left_wrist_speed > p85", repeat_guard_s=2.0),
    SearchOptions(preselect="audio", k=2, seam_decay_s=0.2),
    SearchOptions(control="left_wrist_high", init="mean"),  # the same control as stream 1: one group
    SearchOptions(repeat_guard_s=0.0, k=3),
]


def _speech(scott_dir, i, seconds=25.0):
    wavs = sorted((scott_dir / "inputs").glob("*.wav"))
    x, sr = read_audio(wavs[i % len(wavs)], sr=16000)
    return x[: int(seconds * sr)], sr


def _alone(searcher, options, x, sr, chunk):
    s = searcher.stream(options, sample_rate=sr)
    out = [s.push(x[a:a + chunk]) for a in range(0, x.shape[0], chunk)] + [s.finish()]
    return _joined(out)


def _joined(chunks):
    rot = np.concatenate([c.motion.rotations for c in chunks])
    root = np.concatenate([c.motion.root_positions for c in chunks])
    return rot, root, [s for c in chunks for s in c.steps]


def _batched(batch, streams, speech, chunk):
    """Feed every stream chunk by chunk in lockstep; each round's ready steps searched in one call."""
    outs = [[] for _ in streams]
    errors = {}
    longest = max(x.shape[0] for x in speech)
    for a in range(0, longest, chunk):
        for j, (s, x) in enumerate(zip(streams, speech)):
            if j not in errors and a < x.shape[0]:
                s.feed(x[a:a + chunk])
        while True:
            ready = [(j, sq) for j, s in enumerate(streams) if j not in errors and (sq := s.next_step()) is not None]
            if not ready:
                break
            for (j, sq), got in zip(ready, batch.search([sq for _, sq in ready])):
                if isinstance(got, Exception):
                    errors[j] = got
                else:
                    streams[j].complete_step(sq, *got)
        for j, s in enumerate(streams):
            if j not in errors:
                outs[j].append(s.take_chunk())
    for j, s in enumerate(streams):
        if j not in errors:
            outs[j].append(s.finish())
    return [None if j in errors else _joined(o) for j, o in enumerate(outs)], errors


@pytest.mark.parametrize("method", ["auto", "blocked"])
def test_batched_steps_are_each_streams_own_bit_for_bit(scott_db, scott_dir, method):
    searcher = Searcher(scott_db)
    speech, rates = zip(*[_speech(scott_dir, j, 25.0 - 3 * j) for j in range(len(OPTIONS))])
    chunk = 640  # 40 ms at 16 kHz, as the studio sends
    batch = StepBatch(searcher, method=method)
    streams = [searcher.stream(o, sample_rate=sr) for o, sr in zip(OPTIONS, rates)]
    got, errors = _batched(batch, streams, speech, chunk)
    assert not errors
    relaxed = 0
    for j, o in enumerate(OPTIONS):
        rot, root, steps = _alone(searcher, o, speech[j], rates[j], chunk)
        assert np.array_equal(got[j][0], rot) and np.array_equal(got[j][1], root), j
        assert got[j][2] == steps, j
        relaxed += sum(s["guard_relaxed"] for s in steps)
    # the batches did the work (a handful of steps go alone: the guard left them nothing)
    assert batch.n_batched > 0.9 * (batch.n_batched + batch.n_alone)
    assert batch.n_alone >= relaxed
    # one call per round and group (pre-selection, control bitset): streams 0 and 5, 1 and 4 share theirs
    assert batch.n_calls < batch.n_batched
    assert any(s["control"] for s in got[2][2]) and any(s["repeat_of"] is None for s in got[0][2])


def test_one_streams_failure_is_its_own(scott_db, scott_dir):
    """A stream whose control leaves a step no candidate gets its own explained error from the batch; the
    others go on and get what they get alone."""
    searcher = Searcher(scott_db)
    x, sr = _speech(scott_dir, 0, 8.0)
    # a keyword-free control no window satisfies: the wrist both above its 99th and below its 1st percentile
    bad = SearchOptions(control="left_wrist_height > p99 and left_wrist_height < p1")
    streams = [searcher.stream(SearchOptions(), sample_rate=sr), searcher.stream(bad, sample_rate=sr),
               searcher.stream(SearchOptions(seed=3), sample_rate=sr)]
    with pytest.raises(SearchError) as alone:
        _alone(searcher, bad, x, sr, 640)
    got, errors = _batched(StepBatch(searcher), streams, [x, x, x], 640)
    assert set(errors) == {1} and isinstance(errors[1], SearchError)
    assert str(errors[1]) == str(alone.value)
    for j, o in ((0, SearchOptions()), (2, SearchOptions(seed=3))):
        rot, root, steps = _alone(searcher, o, x, sr, 640)
        assert np.array_equal(got[j][0], rot) and got[j][2] == steps


def test_complete_step_refuses_a_step_of_another_stream(scott_db, scott_dir):
    searcher = Searcher(scott_db)
    x, sr = _speech(scott_dir, 0, 3.0)
    a, b = searcher.stream(None, sample_rate=sr), searcher.stream(None, sample_rate=sr)
    a.feed(x)
    b.feed(x)
    sq = a.next_step()
    res, relaxed = a.search_step(sq)
    with pytest.raises(ParameterError, match="another stream"):
        b.complete_step(sq, res, relaxed)
    a.complete_step(sq, res, relaxed)
    with pytest.raises(ParameterError, match="expected step 1"):
        a.complete_step(sq, res, relaxed)
    with pytest.raises(ParameterError, match="method"):
        StepBatch(searcher, method="fast")


def test_touched_segments_are_those_reading_a_cleared_bit(scott_db):
    """Every segment that reads a bit of a recent window is re-searched under the guard (brute force over all
    segments and ranges, sorted or not)."""
    searcher = Searcher(scott_db)
    batch = StepBatch(searcher)
    start, length = searcher.seg_start, searcher.seg_len
    rng = np.random.default_rng(0)
    for _ in range(200):
        recent = [(int(a), int(a) + int(rng.integers(1, 12))) for a in rng.integers(0, scott_db.n_frames, 3)]
        want = {m for m in range(start.shape[0]) for a, b in recent
                if any(a <= f < b for f in range(start[m] + 1, start[m] + length[m]))}
        assert set(batch._touched(recent).tolist()) == want
    batch._sorted = False
    assert set(batch._touched(recent).tolist()) == want


def test_a_broken_step_does_not_take_the_others_with_it(scott_db, scott_dir):
    """A step whose query cannot be searched (a previous pose of the wrong width) gets its own error; the
    step batched with it gets its own result."""
    searcher = Searcher(scott_db)
    x, sr = _speech(scott_dir, 0, 3.0)
    good, bad = searcher.stream(None, sample_rate=sr), searcher.stream(None, sample_rate=sr)
    good.feed(x)
    bad.feed(x)
    sq_good, sq_bad = good.next_step(), bad.next_step()
    sq_bad.prev = sq_bad.prev[:-1]
    batch = StepBatch(searcher)
    got_good, got_bad = batch.search([sq_good, sq_bad])
    assert isinstance(got_bad, ParameterError) and "pose features" in str(got_bad)
    want = good.search_step(sq_good)
    assert int(got_good[0].frames[0]) == int(want[0].frames[0]) and got_good[1] == want[1]
    assert batch.n_alone == 2  # the group failed as a whole: each step went alone


CHANGE_AT = 10  # step from which a stream's control changes (after its pre-selection was made)
NEW_CONTROL = "hand_speed_low"


def _driven(searcher, options, x, sr, chunk, step_of, applied=None):
    """A stream fed chunk by chunk, each ready step searched by ``step_of(stream, sq)`` (then
    ``applied(stream)``), its control changed to NEW_CONTROL once CHANGE_AT steps have run."""
    s = searcher.stream(options, sample_rate=sr)
    if applied is not None:
        applied(s)
    out, changed = [], False
    for a in range(0, x.shape[0], chunk):
        s.feed(x[a:a + chunk])
        while (sq := s.next_step()) is not None:
            s.complete_step(sq, *step_of(s, sq))
            if applied is not None:
                applied(s)
        if not changed and s.n_steps >= CHANGE_AT:
            s.set_control(NEW_CONTROL)
            changed = True
        out.append(s.take_chunk())
    return _joined(out + [s.finish()])


def test_steps_preselected_ahead_of_their_speech_are_the_usual_ones(scott_db, scott_dir):
    """Each step pre-selected by pose as soon as the step before it is applied (StepBatch.speculate), then
    finished with its audio (StepBatch.finish), gives the windows of the usual search bit for bit: with
    controls, a schedule, the repeat guard and a control changed after the pre-selection (found stale)."""
    searcher = Searcher(scott_db)
    batch = StepBatch(searcher)
    opts = [o for o in OPTIONS if o.preselect == "pose"]
    stats = {"used": 0, "stale": 0, "none": 0}
    ahead: dict = {}

    def usual(s, sq):
        return s.search_step(sq)

    def with_ahead(s, sq):
        up, table = ahead.pop(s, (None, None))
        if up is not None and table is not None and up.same_but_audio(sq):
            stats["used"] += 1
            got = batch.finish(sq, table)
        else:
            stats["stale" if up is not None and table is not None else "none"] += 1
            got = batch.search([sq])[0]
        return got

    def applied(s):
        # the coming step, pre-selected now (a server batches those of many streams in one call)
        up = s.upcoming_step()
        handed = []  # what speculate hands over as each table is complete (a server's sessions get it so)
        table = batch.speculate([up], ready=lambda j, t: handed.append((j, t)))[0]
        assert [(j, t is table) for j, t in handed] == ([] if table is None else [(0, True)])
        ahead[s] = (up, table)

    speech = [_speech(scott_dir, j, 16.0) for j in range(len(opts))]
    for o, (x, sr) in zip(opts, speech):
        rot, root, steps = _driven(searcher, o, x, sr, 640, usual)
        got = _driven(searcher, o, x, sr, 640, with_ahead, applied)
        assert np.array_equal(got[0], rot) and np.array_equal(got[1], root), o
        assert got[2] == steps, o
        assert any(st["repeat_of"] is not None or st["guard_relaxed"] for st in steps) or o.repeat_guard_s == 0
        assert steps[CHANGE_AT]["control"] == NEW_CONTROL
    # every stream's step CHANGE_AT was pre-selected under the old control: found stale, searched as usual
    assert stats["stale"] >= len(opts)
    assert stats["used"] > 0.8 * sum(stats.values())


def test_audio_distances_are_the_tables_own(scott_db, scott_dir):
    """tables.audio_distances over a table's starts gives the kernel's audio distances bit for bit (every
    ISA this machine runs, window lengths 1 to 8), and the spec's cosine distance in float64."""
    from gesturedb import search, tables

    searcher = Searcher(scott_db)
    db = scott_db
    P, A = db.pose_features, db.audio_features
    x, sr = _speech(scott_dir, 1, 4.0)
    q = searcher.query_features(x, sr)
    was = search.get_simd()
    try:
        for isa in search.kernels():
            search.set_simd(isa)
            for n in (1, 3, 8):
                st, dp, da = tables.preselect_table(P, A, searcher.seg_start, searcher.seg_len, P[100],
                                                    q[5:5 + n], allowed=None)
                got = tables.audio_distances(P, A, searcher.seg_start, searcher.seg_len, st, q[5:5 + n])
                assert np.array_equal(got, da), (isa, n)
                # the same from the windows gathered ahead of the audio (what StepBatch.finish reads)
                gathered = tables.gather_windows(P, A, searcher.seg_start, searcher.seg_len, st, n)
                assert np.array_equal(tables.window_distances(gathered, st, q[5:5 + n]), da), (isa, n)
                # the spec in float64 (independent of the kernel)
                m = np.flatnonzero(st >= 0)
                g = searcher.seg_start[m] + st[m]
                win = np.stack([A[g + i] for i in range(n)], axis=1).reshape(len(m), -1).astype(np.float64)
                qv = q[5:5 + n].reshape(-1).astype(np.float64)
                ref = 1 - win @ qv / (np.linalg.norm(win, axis=1) * np.linalg.norm(qv))
                assert np.allclose(got[m], ref, atol=1e-5), (isa, n)
                assert np.all(got[st < 0] == 0)
    finally:
        search.set_simd(was)
    with pytest.raises(ParameterError, match="starts"):
        tables.audio_distances(P, A, searcher.seg_start, searcher.seg_len, st.astype(np.int32), q[:8])
    with pytest.raises(ParameterError, match=r"query_audio: expected 8 frames as the windows; got 3"):
        tables.window_distances(gathered, st, q[:3])
    with pytest.raises(ParameterError, match=r"windows: expected float32 C-contiguous \(M, n, Da\); got float64"):
        tables.window_distances(gathered.astype(np.float64), st, q[:8])
    with pytest.raises(ParameterError, match=r"starts: expected int64 \(3,\)"):
        tables.window_distances(gathered[:3], st, q[:8])
    bad = st.copy()
    bad[np.flatnonzero(st >= 0)[0]] = 0  # s = 0 would read the entry frame's window
    with pytest.raises(ValueError, match=r"expected -1 or 1 <= s"):
        tables.audio_distances(P, A, searcher.seg_start, searcher.seg_len, bad, q[:8])
    with pytest.raises(ValueError, match=r"expected -1 or 1 <= s"):
        tables.gather_windows(P, A, searcher.seg_start, searcher.seg_len, bad, 8)


def test_gathered_windows_are_the_databases(scott_db):
    """tables.gather_windows copies each candidate's window of the audio matrix (zeros for none), for any
    window length, so finishing from it reads the values the scattered path reads."""
    from gesturedb import tables

    searcher = Searcher(scott_db)
    A = scott_db.audio_features
    rng = np.random.default_rng(3)
    for n in (1, 7, 8):
        hi = searcher.seg_len - n
        st = np.where(hi >= 1, rng.integers(1, np.maximum(hi, 1) + 1), -1).astype(np.int64)
        st[::5] = -1
        win = tables.gather_windows(scott_db.pose_features, A, searcher.seg_start, searcher.seg_len, st, n)
        assert win.shape == (st.shape[0], n, A.shape[1]) and win.dtype == np.float32
        for m in range(st.shape[0]):
            g = searcher.seg_start[m] + st[m]
            assert np.array_equal(win[m], A[g:g + n] if st[m] >= 0 else np.zeros((n, A.shape[1]))), (n, m)
