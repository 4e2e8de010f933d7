"""Start-up (issue 39): a stream's first frame does not wait for the derived data built in the background
(the pose projection filter, the seams' typical accelerations), and the frames are the same bits whether
that data is ready from the start, arrives in the middle of the stream, or is never used."""
from __future__ import annotations

import threading

import numpy as np

from gesturedb.io import read_audio
from gesturedb.search import PoseProjection
from gesturedb.synth import Searcher, SearchOptions, assemble
from gesturedb.synth import matching as M


def _gate(monkeypatch, name):
    """Make ``matching.<name>`` wait for the returned event (at most 60 s: a test that forgot it fails)."""
    go = threading.Event()
    real = getattr(M, name)

    def gated(*a, **kw):
        assert go.wait(60), f"{name} was never released"
        return real(*a, **kw)

    monkeypatch.setattr(M, name, gated)
    return go


def _stream_frames(searcher, x, sr, blocks):
    stream = searcher.stream(SearchOptions(), sample_rate=sr)
    chunks = []
    for a, b in blocks:
        chunks.append(stream.push(x[a:b]))
    chunks.append(stream.finish())
    rot = np.concatenate([c.motion.rotations for c in chunks])
    root = np.concatenate([c.motion.root_positions for c in chunks])
    return rot, root, [s for c in chunks for s in c.steps], stream


def test_projection_that_arrives_mid_stream_changes_no_bit(scott_db, scott_dir, monkeypatch):
    x, sr = read_audio(scott_dir / "inputs" / "2_scott_0_2_2.wav", sr=16000)
    half = x.shape[0] // 2
    ready = Searcher(scott_db)
    assert isinstance(ready.pose_projection(), PoseProjection)  # built before the stream: every step filtered
    want = _stream_frames(ready, x, sr, [(0, half), (half, None)])
    plain = _stream_frames(Searcher(scott_db, projection=False), x, sr, [(0, half), (half, None)])

    used = []  # per kernel call: whether it had the projection
    real_search = M.rank_sum_search

    def spy(*a, **kw):
        used.append(kw.get("pose_proj") is not None)
        return real_search(*a, **kw)

    monkeypatch.setattr(M, "rank_sum_search", spy)
    searcher = Searcher(scott_db)
    go = threading.Event()
    build = searcher._build_projection
    searcher._build_projection = lambda: go.wait(60) and build()
    stream = searcher.stream(SearchOptions(), sample_rate=sr)
    first = stream.push(x[:half])
    assert searcher.pose_projection(wait=False) is None  # still building: the steps so far scanned exactly
    n_exact = len(used)
    go.set()
    assert isinstance(searcher.pose_projection(), PoseProjection)
    rest = [stream.push(x[half:]), stream.finish()]
    assert n_exact > 10 and not any(used[:n_exact]) and all(used[n_exact:]) and len(used) > n_exact + 10
    chunks = [first] + rest
    rot = np.concatenate([c.motion.rotations for c in chunks])
    root = np.concatenate([c.motion.root_positions for c in chunks])
    for other in (want, plain):
        assert np.array_equal(rot, other[0]) and np.array_equal(root, other[1])
        assert [s for c in chunks for s in c.steps] == other[2]


def test_first_frame_does_not_wait_for_the_seam_accelerations(scott_db, scott_dir, monkeypatch):
    x, sr = read_audio(scott_dir / "inputs" / "2_scott_0_3_3.wav", sr=16000)
    whole = Searcher(scott_db, projection=False).synthesize(scott_dir / "inputs" / "2_scott_0_3_3.wav")
    M.typical_accelerations(scott_db)  # cached per database: the gate below must hold a fresh computation
    assemble._ACCEL.pop(scott_db, None)
    go = _gate(monkeypatch, "typical_accelerations")
    searcher = Searcher(scott_db, projection=False)
    stream = searcher.stream(SearchOptions(), sample_rate=sr)
    job = searcher._accel_job
    first = None
    for a in range(0, x.shape[0], 640):  # 40 ms blocks until a frame comes
        first = stream.push(x[a:a + 640])
        if first.n_frames:
            break
    assert first.n_frames > 0 and stream.n_steps == 1 and not job.ready()
    go.set()
    rest = [stream.push(x[a + 640:]), stream.finish()]
    assert job.ready()
    rot = np.concatenate([c.motion.rotations for c in [first] + rest])
    assert np.array_equal(rot, whole.motion.rotations)
    assert [s for c in [first] + rest for s in c.steps] == whole.steps
