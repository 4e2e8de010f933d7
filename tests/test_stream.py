"""The live k-NN synthesis (issue 39): a stream fed in chunks gives the frames of the whole-file synthesis,
bit for bit, on the real inputs with controls and a schedule; frames come out within the stated latency."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.io import read_audio
from gesturedb.synth import Searcher, SearchOptions, methods
from gesturedb.synth.stream import Stream, StreamChunk

SCHEDULE = "0-20: left_wrist_height > p60; 30-: left_wrist_slow"


def _feed(stream: Stream, x: np.ndarray, rng, *, most: int = 9000) -> list[StreamChunk]:
    out, i = [], 0
    while i < len(x):
        n = int(rng.integers(1, most))
        out.append(stream.push(x[i:i + n]))
        i += n
    out.append(stream.finish())
    return out


def _joined(chunks):
    assert [c.start for c in chunks] == list(np.cumsum([0] + [c.n_frames for c in chunks[:-1]]))
    rot = np.concatenate([c.motion.rotations for c in chunks])
    root = np.concatenate([c.motion.root_positions for c in chunks])
    return rot, root, [s for c in chunks for s in c.steps]


@pytest.mark.parametrize("stem, options", [
    ("2_scott_0_2_2", SearchOptions(control=SCHEDULE)),
    ("2_scott_0_3_3", SearchOptions(control="left_wrist_high", seed=5, repeat_guard_s=2.0)),
    ("2_scott_0_4_4", SearchOptions(control="0-10: symmetric; 10-: left_wrist_speed > p85", preselect="audio",
                                    seam_decay_s=0.2)),
])
def test_stream_in_chunks_is_the_whole_file_synthesis_bit_for_bit(scott_db, scott_dir, stem, options):
    wav = scott_dir / "inputs" / f"{stem}.wav"
    searcher = Searcher(scott_db)
    whole = searcher.synthesize(wav, options=options)
    x, sr = read_audio(wav, sr=16000)
    for seed in (0, 1):
        chunks = _feed(searcher.stream(options, sample_rate=sr), x, np.random.default_rng(seed))
        rot, root, steps = _joined(chunks)
        assert np.array_equal(rot, whole.motion.rotations) and np.array_equal(root, whole.motion.root_positions)
        assert steps == whole.steps
    assert any(s["control"] for s in whole.steps)


def test_the_end_in_parts_is_the_same_end(scott_db, scott_dir):
    """``end_speech`` and the last steps one at a time (as a server runs them, with other streams' steps), then
    ``finish``: the frames and steps of the whole-file synthesis, the last step shorter than the others."""
    wav = scott_dir / "inputs" / "2_scott_0_5_5.wav"
    searcher = Searcher(scott_db)
    whole = searcher.synthesize(wav)
    assert whole.steps[-1]["out_end"] - whole.steps[-1]["out_start"] < 8  # the speech ends within a step
    x, sr = read_audio(wav, sr=16000)
    stream = searcher.stream(sample_rate=sr)
    chunks = [stream.push(x)]
    assert stream.upcoming_step() is not None
    stream.end_speech()
    assert stream.upcoming_step() is None  # no coming step to pre-select: the speech is over
    last = []
    while (sq := stream.next_step()) is not None:
        last.append(sq.n)
        stream.complete_step(sq, *stream.search_step(sq))
    assert last and last[-1] < 8
    chunks += [stream.take_chunk(), stream.finish()]
    rot, root, steps = _joined(chunks)
    assert np.array_equal(rot, whole.motion.rotations) and np.array_equal(root, whole.motion.root_positions)
    assert steps == whole.steps
    again = searcher.stream(sample_rate=sr)
    again.push(x[: sr])
    again.end_speech()
    with pytest.raises(ParameterError, match=r"Stream.push: the stream's speech has ended \(end_speech\)"):
        again.push(x[:10])
    with pytest.raises(ParameterError, match="Stream.end_speech: the speech of this stream has already ended"):
        again.end_speech()


def test_a_stream_told_its_length_knows_its_last_step_ahead(scott_db, scott_dir):
    """With ``n_samples`` the coming step that the speech's end makes shorter is known before the end
    (``upcoming_step``: what a server pre-selects), the same step ``next_step`` gives after ``end_speech``;
    the frames are those of the whole file whatever length was told (a wrong one only gives full coming steps)."""
    wav = scott_dir / "inputs" / "2_scott_0_5_5.wav"
    searcher = Searcher(scott_db)
    whole = searcher.synthesize(wav)
    last_n = whole.steps[-1]["out_end"] - whole.steps[-1]["out_start"]
    assert last_n < 8
    x, sr = read_audio(wav, sr=16000)
    for told, coming in ((len(x), last_n), (len(x) // 2, 8), (len(x) + 5 * sr, 8), (None, 8)):
        stream = searcher.stream(sample_rate=sr, n_samples=told)
        chunks = [stream.push(x)]
        up = stream.upcoming_step()
        assert stream.n_steps == len(whole.steps) - 1  # what follows is the last step
        assert up.n == coming, told
        stream.end_speech()
        sq = stream.next_step()
        assert sq.n == last_n and up.same_but_audio(sq) == (coming == last_n), told
        stream.complete_step(sq, *stream.search_step(sq))
        chunks.append(stream.finish())
        rot, root, steps = _joined(chunks)
        assert np.array_equal(rot, whole.motion.rotations) and np.array_equal(root, whole.motion.root_positions)
        assert steps == whole.steps
    assert searcher.stream(sample_rate=sr, n_samples=len(x)).n_steps == 0
    for bad in (-1, 2.5, True):
        with pytest.raises(ParameterError, match="n_samples: expected the speech's length as an int >= 0 or None"):
            Stream(scott_db, sample_rate=sr, n_samples=bad)


def test_set_control_takes_effect_from_the_next_step(scott_db, scott_dir):
    wav = scott_dir / "inputs" / "2_scott_0_2_2.wav"
    x, sr = read_audio(wav, sr=16000)
    searcher = Searcher(scott_db)
    stream = Stream(scott_db, SearchOptions(control="left_wrist_high"), sample_rate=sr, searcher=searcher)
    chunks = [stream.push(x[: 20 * sr])]
    i = stream.n_steps
    assert i > 20
    stream.set_control("left_wrist_slow")
    chunks.append(stream.push(x[20 * sr: 40 * sr]))
    j = stream.n_steps
    stream.set_control(None)
    chunks.append(stream.push(x[40 * sr:]))
    chunks.append(stream.finish())
    rot, root, steps = _joined(chunks)
    t0, t1 = i * stream.step / scott_db.fps, j * stream.step / scott_db.fps
    assert steps[j]["control"] is None and steps[j - 1]["control"] == "left_wrist_slow"
    assert [s["control"] for s in steps[i - 1:i + 1]] == ["left_wrist_high", "left_wrist_slow"]
    # the same as the whole file with the schedule those calls make
    whole = searcher.synthesize(wav, control=f"0-{t0:.6f}: left_wrist_high; {t0:.6f}-{t1:.6f}: left_wrist_slow")
    assert np.array_equal(rot, whole.motion.rotations) and [s["control"] for s in steps] == \
        [s["control"] for s in whole.steps]
    with pytest.raises(ParameterError, match="unknown mask name 'nodding'"):
        Stream(scott_db, sample_rate=sr).set_control("nodding")


def test_frames_come_out_within_the_stated_latency(scott_db, scott_dir):
    x, sr = read_audio(scott_dir / "inputs" / "2_scott_0_3_3.wav", sr=16000)
    stream = methods.get("knn").open(scott_db).stream(SearchOptions(), sample_rate=sr)
    assert methods.get("knn").streams and 0.5 < stream.latency_s < 2.5
    hop = sr // 10
    late = 0
    for a in range(0, len(x), hop):
        chunk = stream.push(x[a:a + hop])
        heard_s = min(len(x), a + hop) / sr
        # every frame whose audio (and the context the stream states) has come is out
        due = int(np.floor((heard_s - stream.latency_s) * scott_db.fps))
        late = max(late, due - stream.n_frames_out)
        assert chunk.motion.rotations.shape[0] == chunk.n_frames
    assert late <= 0, late
    last = stream.finish()
    assert stream.n_frames_out == last.start + last.n_frames
    with pytest.raises(ParameterError, match="finished"):
        stream.push(x[:10])


def test_what_a_stream_refuses(scott_db):
    with pytest.raises(ParameterError, match="smooth: a stream cannot smooth"):
        Stream(scott_db, SearchOptions(smooth=True), sample_rate=16000)
    with pytest.raises(ParameterError, match="sample_rate: expected a positive int"):
        Stream(scott_db, sample_rate=0)
    s = Stream(scott_db, sample_rate=16000)
    assert s.push(np.zeros(100, np.float32)).n_frames == 0
    with pytest.raises(ParameterError, match=r"audio: expected at least one search step \(8 frames = 0.53 s\)"):
        s.finish()
