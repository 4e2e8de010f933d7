"""Segmentation: gesturedb.features.segments."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.features.segments import Clips, fixed_chunks, word_gap_clips


@pytest.mark.parametrize("n,length", [(0, 64), (1, 64), (63, 64), (64, 64), (65, 64), (1906, 64), (10, 1), (7, 3)])
def test_fixed_chunks_tile_the_recording(n, length):
    start, lens = fixed_chunks(n, length=length)
    assert start.dtype == np.int64 and lens.dtype == np.int64
    assert len(start) == -(-n // length)
    covered = np.concatenate([np.arange(s, s + ln) for s, ln in zip(start, lens)]) if n else np.zeros(0)
    np.testing.assert_array_equal(covered, np.arange(n))
    assert (lens[:-1] == length).all()
    if n:
        assert lens[-1] == n - length * (len(start) - 1)  # the short tail is kept


def test_fixed_chunks_bad_arguments():
    with pytest.raises(ParameterError, match="length: expected an int >= 1; got 0"):
        fixed_chunks(10, length=0)
    with pytest.raises(ParameterError, match="n_frames: expected an int >= 0; got -3"):
        fixed_chunks(-3)


def _check_clips(clips: Clips, ws, we, n_frames, fps, gap_s):
    """The properties word_gap_clips promises, checked directly."""
    start, length, w0, w1 = clips
    for a in clips:
        assert a.dtype == np.int64
    # clips tile [0, n_frames) in order
    assert start[0] == 0 and (length >= 1).all()
    np.testing.assert_array_equal(start[1:], start[:-1] + length[:-1])
    assert start[-1] + length[-1] == n_frames
    # every word belongs to exactly one clip
    assert w0[0] == 0 and w1[-1] == len(ws)
    np.testing.assert_array_equal(w0[1:], w1[:-1])
    owner = np.repeat(np.arange(len(start)), w1 - w0)
    assert len(owner) == len(ws)
    # no long pause inside a clip; a long pause between every two clips
    for c in range(len(start)):
        inner = range(w0[c], w1[c] - 1)
        for w in inner:
            assert ws[w + 1] - np.max(we[: w + 1]) <= gap_s
        if c > 0 and w0[c] > 0:
            assert ws[w0[c]] - np.max(we[: w0[c]]) > gap_s
    # each word starts inside its own clip (words inside the recording)
    for w in range(len(ws)):
        frame = int(np.floor(ws[w] * fps))
        if frame < n_frames:
            c = owner[w]
            assert start[c] <= frame < start[c] + length[c], (w, c)


def test_known_split():
    ws = np.array([0.5, 1.0, 1.5, 3.0, 3.4, 6.0])
    we = np.array([0.9, 1.4, 2.0, 3.3, 3.9, 6.5])
    clips = word_gap_clips(ws, we, n_frames=240, fps=30)
    # pauses: 2.0 -> 3.0 (mid 2.5 s = frame 75), 3.9 -> 6.0 (mid 4.95 s = frame 148.5 -> 149)
    np.testing.assert_array_equal(clips.start, [0, 75, 149])
    np.testing.assert_array_equal(clips.length, [75, 74, 91])
    np.testing.assert_array_equal(clips.word_start, [0, 3, 5])
    np.testing.assert_array_equal(clips.word_end, [3, 5, 6])
    _check_clips(clips, ws, we, 240, 30, 0.4)


def test_pause_exactly_at_the_threshold_does_not_split():
    ws = np.array([0.0, 1.5])
    we = np.array([1.0, 2.0])
    assert len(word_gap_clips(ws, we, n_frames=90, fps=30, gap_s=0.5).start) == 1
    assert len(word_gap_clips(ws, we, n_frames=90, fps=30, gap_s=0.49).start) == 2


def test_overlapping_words_use_the_running_end():
    # word 1 lies inside word 0; the pause before word 2 starts at word 0's end
    ws = np.array([0.0, 0.2, 1.2])
    we = np.array([1.0, 0.3, 1.5])
    clips = word_gap_clips(ws, we, n_frames=60, fps=30)
    assert len(clips.start) == 1


@pytest.mark.parametrize("seed", range(20))
def test_random_transcripts_satisfy_the_properties(seed):
    rng = np.random.default_rng(seed)
    fps = float(rng.choice([25.0, 30.0, 60.0, 29.97]))
    n_words = int(rng.integers(0, 80))
    gaps = rng.choice([0.05, 0.2, 0.39, 0.41, 0.8, 2.0], size=n_words) * rng.uniform(0.8, 1.2, n_words)
    durs = rng.uniform(0.05, 0.6, n_words)
    ws = np.cumsum(gaps) + np.concatenate([[0.0], np.cumsum(durs)[:-1]])
    we = ws + durs
    end_s = (we[-1] if n_words else 0.0) + rng.uniform(0.1, 2.0)
    n_frames = max(1, int(end_s * fps))
    clips = word_gap_clips(ws, we, n_frames=n_frames, fps=fps)
    _check_clips(clips, ws, we, n_frames, fps, 0.4)


def test_no_words_and_no_frames():
    one = word_gap_clips([], [], n_frames=100, fps=30)
    assert one.start.tolist() == [0] and one.length.tolist() == [100]
    assert one.word_start.tolist() == [0] and one.word_end.tolist() == [0]
    none = word_gap_clips([0.1], [0.2], n_frames=0, fps=30)
    assert all(len(a) == 0 for a in none)


def test_words_past_the_end_join_the_last_clip():
    ws = np.array([0.1, 2.0, 5.0, 8.0])
    we = np.array([0.5, 2.5, 5.5, 8.5])
    clips = word_gap_clips(ws, we, n_frames=90, fps=30)  # the motion ends at 3 s
    np.testing.assert_array_equal(clips.start, [0, 38])
    np.testing.assert_array_equal(clips.word_end, [1, 4])
    assert clips.start[-1] + clips.length[-1] == 90


def test_real_transcript(scott_dir):
    from praatio import textgrid

    tg = textgrid.openTextgrid(str(scott_dir / "2_scott_0_1_1.TextGrid"), includeEmptyIntervals=False)
    words = [e for e in tg.getTier("words").entries if e.label.strip()]
    ws = np.array([w.start for w in words])
    we = np.array([w.end for w in words])
    clips = word_gap_clips(ws, we, n_frames=1906, fps=30)
    _check_clips(clips, ws, we, 1906, 30, 0.4)
    seconds = clips.length / 30
    # GestureMaster's clips last from about 1 s to over 10 s
    assert 3 <= len(clips.start) <= 40
    assert np.median(seconds) > 1.0


def test_bad_word_timings():
    with pytest.raises(ParameterError, match="word_start_s: expected times sorted ascending; got 2.000 s then 1.000 s at word 1"):
        word_gap_clips([2.0, 1.0], [2.5, 1.5], n_frames=90, fps=30)
    with pytest.raises(ParameterError, match="word_end_s: expected end >= start; got word 0"):
        word_gap_clips([2.0], [1.0], n_frames=90, fps=30)
    with pytest.raises(ParameterError, match="equal length"):
        word_gap_clips([1.0, 2.0], [1.5], n_frames=90, fps=30)
    with pytest.raises(ParameterError, match="gap_s: expected seconds > 0"):
        word_gap_clips([1.0], [1.5], n_frames=90, fps=30, gap_s=0)
    with pytest.raises(ParameterError, match="finite"):
        word_gap_clips([np.nan], [1.5], n_frames=90, fps=30)
