"""Keyword sub-databases (gesturedb.db.keywords, gesturedb.cli.keywords).

Hand-made databases (recordings + words only) pin the stretch arithmetic, the
whole-word matching and the per-step choice against brute force in exact
rational arithmetic; a database built from the real BEAT2 recording checks the
edits, the export and the detection in real TextGrid and GENEA TSV transcripts.
"""
from __future__ import annotations

import argparse
import hashlib
import math
import os
import shutil
from fractions import Fraction

import numpy as np
import pytest

import gesturedb
from gesturedb import control as masks
from gesturedb.db import keywords as kw
from gesturedb.db import schema
from gesturedb.db.export import export_keyword
from gesturedb.errors import GestureDBError, ParameterError
from gesturedb.io.transcripts import Words, read_transcript

# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------


def _write_small_db(path, *, fps, recordings, words):
    """A database file with only the recordings and words tables (enough for keyword edits).

    recordings : list of (name, n_frames); words : list of (recording index, start_s, end_s, text)
    """
    import h5py

    n = [r[1] for r in recordings]
    starts = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64)
    with h5py.File(path, "w") as h5:
        dims: dict = {}
        h5.attrs["schema_version"] = schema.SCHEMA_VERSION
        h5.attrs["fps"] = float(fps)
        h5.attrs["n_frames"] = int(sum(n))
        W = schema.write
        W(h5, "recordings/name", [r[0] for r in recordings], dims)
        W(h5, "recordings/speaker", ["test"] * len(n), dims)
        for col in ("motion_path", "audio_path", "transcript_path"):
            W(h5, f"recordings/{col}", [""] * len(n), dims)
        W(h5, "recordings/start_frame", starts, dims)
        W(h5, "recordings/n_frames", np.asarray(n, dtype=np.int64), dims)
        W(h5, "recordings/duration_s", np.asarray(n, dtype=np.float64) / fps, dims)
        W(h5, "recordings/source_fps", np.full(len(n), float(fps)), dims)
        W(h5, "recordings/mirrored", np.zeros(len(n), dtype=bool), dims)
        W(h5, "words/recording", np.asarray([w[0] for w in words], dtype=np.int32), dims)
        W(h5, "words/start_s", np.asarray([w[1] for w in words], dtype=np.float64), dims)
        W(h5, "words/end_s", np.asarray([w[2] for w in words], dtype=np.float64), dims)
        W(h5, "words/text", [w[3] for w in words], dims)
    return path


def _frac(x) -> Fraction:
    # decimal literals as exact rationals, so boundary cases are decided exactly
    return Fraction(str(x)) if isinstance(x, float) else Fraction(x)


def _brute_frames(a_s, b_s, fps, n_frames) -> set[int]:
    """Frames f in [0, n_frames) whose span [f/fps, (f+1)/fps) overlaps [a_s, b_s), exactly."""
    a, b, fps = _frac(a_s), _frac(b_s), _frac(fps)
    if b == a:  # a zero-length interval is still said in the frame containing it
        return {math.floor(a * fps)} & set(range(n_frames))
    return {f for f in range(n_frames) if Fraction(f) / fps < b and Fraction(f + 1) / fps > a}


def _cli_module(name):
    """A command module, gesturedb.cli.<name>."""
    import importlib

    return importlib.import_module(f"gesturedb.cli.{name}")


def _sha(path) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def _cli(argv, capsys):
    """Run `gesturedb keywords ...` through the module's own parser, as gesturedb.cli.main will."""
    cli_kw = _cli_module("keywords")
    parser = argparse.ArgumentParser(prog="gesturedb")
    sub = parser.add_subparsers(dest="command", required=True)
    cli_kw.add_parser(sub)
    args = parser.parse_args(["keywords", *argv])
    rc = args.run(args)
    return rc, capsys.readouterr().out


# --------------------------------------------------------------------------
# hand-made database
# --------------------------------------------------------------------------

FPS = 10
RECS = [("a", 50), ("b", 30)]  # 5 s and 3 s; global frames [0, 50) and [50, 80)
WORDS = [
    (0, 0.2, 0.5, "Time,"),        # 0: matches (case, punctuation); stretch clipped at 0
    (0, 0.5, 0.9, "flies"),        # 1
    (0, 1.0, 1.3, "times"),        # 2: not a whole-word match
    (0, 2.0, 2.6, "there time"),   # 3: a multi-word entry matches each of its words
    (0, 4.5, 4.9, "TIME"),         # 4: stretch clipped at the recording end
    (1, 0.0, 0.3, "time"),         # 5: clipped at the start of recording b, not into a
    (1, 1.0, 1.5, "handle"),       # 6
    (1, 2.95, 3.4, "time"),        # 7: starts inside, ends after the motion
    (1, 3.2, 3.5, "time"),         # 8: starts after the motion: skipped
]


@pytest.fixture
def small_db(tmp_path):
    return _write_small_db(tmp_path / "small.h5", fps=FPS, recordings=RECS, words=WORDS)


@pytest.mark.parametrize("fps", [10, 15, 30, 25])
def test_time_to_frames_matches_exact_overlap(fps):
    # Transcript times are decimals (TextGrid, TSV). Many land exactly on frame
    # boundaries k / fps, where float products like 2.3 * 10 = 22.999999999999996
    # must still give frame 23: compare with exact rational arithmetic.
    rng = np.random.default_rng(fps)
    starts = np.round(rng.uniform(0, 5, 400), 1)
    ends = np.round(starts + rng.uniform(0, 1, 400), 2)
    ends[:20] = starts[:20]  # zero-length words
    first, stop = kw.time_to_frames(starts, ends, fps)
    on_boundary = 0
    for s, e, a, b in zip(starts.tolist(), ends.tolist(), first, stop):
        want = _brute_frames(s, e, fps, 400)
        assert set(range(int(a), int(b))) == want, (s, e)
        on_boundary += (_frac(s) * fps).denominator == 1
    assert on_boundary > 20  # the boundary case is really exercised


def test_find_occurrences_handmade(small_db):
    before, after = 0.5, 1.0
    with gesturedb.open(small_db) as db:
        sub = kw.find_occurrences(db, "TIME", before_s=before, after_s=after)
    assert sub.word == "time"
    np.testing.assert_array_equal(sub.word_index, [0, 3, 4, 5, 7])
    assert sub.definition["found"] == 6 and sub.definition["skipped"] == 1
    assert sub.definition["matched"] == sorted({"Time,", "there time", "TIME", "time"})
    starts = {0: 0, 1: 50}
    expect_bits = np.zeros(80, dtype=bool)
    for k, wi in enumerate(sub.word_index):
        rec, s, e, _ = WORDS[wi]
        n = RECS[rec][1]
        frames = _brute_frames(_frac(s) - _frac(before), _frac(e) + _frac(after), FPS, n)
        assert frames == set(range(int(sub.start[k]) - starts[rec], int(sub.start[k] + sub.length[k]) - starts[rec]))
        assert sub.recording[k] == rec
        expect_bits[[starts[rec] + f for f in frames]] = True
    np.testing.assert_array_equal(masks.unpack_bits(sub.mask, 80), expect_bits)
    # clipping: at the start of a, at the end of a (not running into b), at the start of b
    assert sub.start[0] == 0 and sub.start[2] + sub.length[2] == 50 and sub.start[3] == 50
    assert sub.start[4] + sub.length[4] == 80


def test_add_keyword_handmade_roundtrip_and_errors(small_db):
    sub = kw.add_keyword(small_db, "time", before_s=0.2, after_s=0.3)
    with gesturedb.open(small_db) as db:
        subs = kw.subdatabases(db)
        again = kw.find_occurrences(db, "time", before_s=0.2, after_s=0.3)
        assert set(subs) == {"time"}
        got = subs["time"]
        for name in ("start", "length", "recording", "word_index", "mask"):
            np.testing.assert_array_equal(getattr(got, name), getattr(sub, name))
            np.testing.assert_array_equal(getattr(got, name), getattr(again, name))
            assert getattr(got, name).dtype == np.dtype(kw.SUBDB_FIELDS[name][0])
        assert got.definition == {**again.definition}
        assert (got.before_s, got.after_s) == (0.2, 0.3)
        h = db.h5[f"{schema.SUBDB_GROUP}/time"]
        assert h["mask"].attrs["unit"] == "" and "bitset" in h["mask"].attrs["doc"]
    with pytest.raises(ParameterError, match=r"keyword 'time'.*already has its sub-database.*replace"):
        kw.add_keyword(small_db, "Time")
    sub2 = kw.add_keyword(small_db, "Time", before_s=0.0, after_s=0.0, replace=True)
    assert (sub2.before_s, sub2.after_s) == (0.0, 0.0)
    with pytest.raises(ParameterError,
                       match=r"keyword 'tme': not among the 9 words of .*small\.h5; close words: 'time'"):
        kw.add_keyword(small_db, "tme")
    with pytest.raises(ParameterError, match=r"keyword: expected a single word"):
        kw.add_keyword(small_db, "time flies")
    with pytest.raises(ParameterError, match=r"before_s: expected a non-negative number of seconds, got -1"):
        kw.add_keyword(small_db, "flies", before_s=-1)
    with pytest.raises(ParameterError, match=r"keyword: expected a word with at least one letter"):
        kw.add_keyword(small_db, "<sil>")


def test_words_before_the_motion_are_skipped_not_negative_stretches(tmp_path):
    # issue 41: a database built before the readers refused negative times held them, and
    # `keywords add` reported "4 occurrence(s), -58269 frames"
    words = [(0, -3.0, -2.5, "wave"), (0, -0.35, 0.15, "wave"), (0, 1.0, 1.2, "wave"), (1, -9.0, -8.0, "only")]
    path = _write_small_db(tmp_path / "neg.h5", fps=FPS, recordings=RECS, words=words)
    sub = kw.add_keyword(path, "wave", before_s=0.5, after_s=0.5)
    np.testing.assert_array_equal(sub.word_index, [1, 2])
    assert sub.definition["skipped"] == 1 and (sub.length > 0).all() and sub.n_frames > 0
    np.testing.assert_array_equal(sub.start, [0, 5])
    np.testing.assert_array_equal(sub.length, [7, 12])  # [0, ceil(0.65 * 10)) and [0.5 s, 1.7 s)
    with pytest.raises(ParameterError, match=r"keyword 'only': all 1 occurrence\(s\) in .*neg\.h5 lie outside the "
                                             r"motion of their recording \(after its end, or before its start\)"):
        kw.add_keyword(path, "only")


def test_list_words_counts(small_db):
    with gesturedb.open(small_db) as db:
        rows = kw.list_words(db)
        top2 = kw.list_words(db, top=2)
    by = {r.word: r for r in rows}
    # "there time" counts for both words, its 0.6 s shared equally
    assert by["time"].count == 6 and by["there"].count == 1
    assert by["time"].total_s == pytest.approx(0.3 + 0.3 + 0.4 + 0.3 + 0.45 + 0.3)
    assert by["there"].total_s == pytest.approx(0.3)
    assert [r.count for r in rows] == sorted((r.count for r in rows), reverse=True)
    assert top2 == rows[:2] and rows[0].word == "time"
    assert sum(r.count for r in rows) == sum(len(w[3].split()) for w in WORDS)


def _small_db_with_keywords(path):
    _write_small_db(path, fps=FPS, recordings=[("a", 100)], words=[
        (0, 0.5, 0.7, "flies"), (0, 2.0, 2.4, "time"), (0, 6.0, 6.5, "arrow"), (0, 8.0, 8.2, "time")])
    kw.add_keyword(path, "time", before_s=0.0, after_s=0.0)
    kw.add_keyword(path, "flies", before_s=0.0, after_s=0.0)
    return path


def test_keyword_step_masks_choice_and_boundaries(tmp_path):
    path = _small_db_with_keywords(tmp_path / "kw.h5")
    # step = 4 frames at 10 fps. "flies" [0.25, 0.55) covers frames 2-5: the step
    # boundary at frame 4 is in the middle of the word. "time" [0.5, 0.75) covers
    # 5-7: step 1 has 3 frames of "time" and 2 of "flies". Step 4 (16-19): 2 frames
    # each, "flies" first. "Arrow" has no sub-database; "TIME!" at the very end is
    # cut by n_out_frames.
    words = Words([0.25, 0.5, 1.6, 1.8, 2.2, 2.88], [0.55, 0.75, 1.8, 2.0, 2.6, 3.5],
                  ["flies", "Time", "flies", "time", "arrow", "TIME!"])
    n_out, step = 30, 4
    n_steps = -(-n_out // step)
    with gesturedb.open(path) as db:
        subs = kw.subdatabases(db)
        bits, labels = kw.keyword_step_masks(db, words, n_steps=n_steps, step=step, n_out_frames=n_out)
        F = db.n_frames
    assert bits.shape == (n_steps, masks.n_words(F)) and bits.dtype == np.uint64 and bits.flags.c_contiguous
    assert labels == ["flies", "time", None, None, "flies", None, None, "time"]
    # independent check: which keywords overlap each step, in exact seconds
    for i in range(n_steps):
        t0, t1 = Fraction(i * step, FPS), Fraction(min((i + 1) * step, n_out), FPS)
        over = {}
        for s, e, w in zip(words.start_s, words.end_s, words.text):
            k = kw.normalise_word(w)
            lo, hi = max(_frac(s), t0), min(_frac(e), t1)
            if k in subs and hi > lo:
                over[k] = over.get(k, 0) + (hi - lo)
        if labels[i] is None:
            assert not over
            np.testing.assert_array_equal(bits[i], masks.full_mask(F))
        else:
            assert labels[i] in over
            np.testing.assert_array_equal(bits[i], subs[labels[i]].mask)
    # restricting to one keyword gives the mid-word step to it
    with gesturedb.open(path) as db:
        _, labels1 = kw.keyword_step_masks(db, words, n_steps=n_steps, step=step, n_out_frames=n_out, only=["FLIES"])
    assert labels1 == ["flies", "flies", None, None, "flies", None, None, None]


def test_keyword_step_masks_none_and_errors(tmp_path):
    path = _small_db_with_keywords(tmp_path / "kw.h5")
    with gesturedb.open(path) as db:
        no_kw = Words([0.0, 1.0], [0.5, 1.5], ["arrow", "banana"])
        assert kw.keyword_step_masks(db, no_kw, n_steps=3, step=8, n_out_frames=20) is None
        # a keyword said after the end of the output does not count
        late = Words([5.0], [5.5], ["time"])
        assert kw.keyword_step_masks(db, late, n_steps=3, step=8, n_out_frames=20) is None
        said = Words([0.0], [0.5], ["time"])
        assert kw.keyword_step_masks(db, said, n_steps=3, step=8, n_out_frames=20, only=["flies"]) is None
        # "arrow" is a word of the database but has no sub-database: only the keywords are offered
        with pytest.raises(ParameterError, match=r"keyword 'arow': no such sub-database in .*kw\.h5; keywords: flies, time$"):
            kw.keyword_step_masks(db, said, n_steps=3, step=8, n_out_frames=20, only=["arow"])
        with pytest.raises(ParameterError,
                           match=r"n_steps: expected ceil\(n_out_frames / step\) = ceil\(20 / 8\) = 3, got 2"):
            kw.keyword_step_masks(db, said, n_steps=2, step=8, n_out_frames=20)
        with pytest.raises(ParameterError, match=r"step: expected an integer >= 1, got 0"):
            kw.keyword_step_masks(db, said, n_steps=3, step=0, n_out_frames=20)
        with pytest.raises(ParameterError, match=r"transcript: expected a path or a Words object"):
            kw.keyword_step_masks(db, [(0.0, 0.5, "time")], n_steps=3, step=8, n_out_frames=20)


def test_keyword_step_masks_without_subdatabases(small_db):
    with gesturedb.open(small_db) as db:
        assert kw.subdatabases(db) == {}
        assert kw.keyword_step_masks(db, Words([0.0], [0.5], ["time"]), n_steps=1, step=8, n_out_frames=5) is None


def test_remove_and_drop_handmade(small_db):
    kw.add_keyword(small_db, "time")
    with gesturedb.open(small_db) as db:
        before = kw.subdatabases(db)["time"]
        rows = kw.show(db, "time")
    assert [r.index for r in rows] == list(range(len(before)))
    new = kw.remove_occurrence(small_db, "time", 1)
    with gesturedb.open(small_db) as db:
        after = kw.subdatabases(db)["time"]
    keep = [0, 2, 3, 4]
    np.testing.assert_array_equal(after.word_index, before.word_index[keep])
    np.testing.assert_array_equal(after.start, before.start[keep])
    assert after.definition["removed"] == [int(before.word_index[1])]
    np.testing.assert_array_equal(new.mask, after.mask)
    # the mask is the union of what is left: word 3's frames [15, 36) minus its overlap with word 0's [0, 15)
    bits = masks.unpack_bits(after.mask, 80)
    want = np.zeros(80, dtype=bool)
    for a, n in zip(after.start, after.length):
        want[a:a + n] = True
    np.testing.assert_array_equal(bits, want)
    assert not bits[20:36].any() and bits[:15].all()
    with pytest.raises(ParameterError, match=r"index: expected an occurrence of 'time' in \[0, 4\).*got 4"):
        kw.remove_occurrence(small_db, "time", 4)
    for _ in range(3):
        kw.remove_occurrence(small_db, "time", 0)
    with pytest.raises(ParameterError, match=r"occurrence 0 is the last one .*drop"):
        kw.remove_occurrence(small_db, "time", 0)
    dropped = kw.drop_keyword(small_db, "time")
    assert len(dropped) == 1
    with gesturedb.open(small_db) as db:
        assert kw.subdatabases(db) == {} and schema.SUBDB_GROUP not in db.h5
    with pytest.raises(ParameterError, match=r"keyword 'time': .* has no keyword sub-databases"):
        kw.drop_keyword(small_db, "time")


# --------------------------------------------------------------------------
# real data
# --------------------------------------------------------------------------


@pytest.fixture(scope="session")
def built_db(scott_dir, tmp_path_factory):
    """The BEAT2 recording built once per session (motion + speech + TextGrid)."""
    path = tmp_path_factory.mktemp("kwdb") / "scott.h5"
    gesturedb.build([scott_dir], path).close()
    return path


@pytest.fixture(scope="session")
def keyword_db(built_db, tmp_path_factory):
    """A copy of the built database with the sub-databases of 'time' and 'like' (read-only in the tests)."""
    path = tmp_path_factory.mktemp("kwdb2") / "scott_keywords.h5"
    shutil.copyfile(built_db, path)
    kw.add_keyword(path, "time")
    kw.add_keyword(path, "like")
    return path


@pytest.fixture
def db_copy(built_db, tmp_path):
    dst = tmp_path / "scott.h5"
    shutil.copyfile(built_db, dst)
    return dst


def _expected_steps(words, keyword, *, fps, step, n_out):
    """Steps whose output span overlaps an occurrence of `keyword`, decided in exact seconds (not frames)."""
    hit = set()
    fps = _frac(fps)
    for s, e, text in zip(words.start_s, words.end_s, words.text):
        if keyword not in kw.normalise_word(text).split():
            continue
        s, e = _frac(s), _frac(e)
        for i in range(-(-n_out // step)):
            t0, t1 = i * step / fps, min((i + 1) * step, n_out) / fps
            # a word overlaps the step if it is said during it (a zero-length word at its instant)
            if (s < t1 and e > t0) or (s == e and t0 <= s < t1):
                hit.add(i)
    return hit


@pytest.mark.parametrize("transcript,keyword", [
    ("beat2-scott/inputs/2_scott_0_2_2.TextGrid", "time"),
    ("genea2023-transcripts/trn_2023_v0_000_main-agent.tsv", "like"),
])
def test_keyword_detection_in_real_transcripts(keyword_db, data_dir, transcript, keyword):
    words = read_transcript(data_dir / transcript)
    n_out = int(math.ceil(float(words.end_s.max()) * 15)) + 5
    with gesturedb.open(keyword_db) as db:
        assert db.fps == 15
        sub = kw.subdatabases(db)[keyword]
        full = masks.full_mask(db.n_frames)
        split_seen = False
        for step in (8, 7, 5, 3):
            n_steps = -(-n_out // step)
            res = kw.keyword_step_masks(db, data_dir / transcript, n_steps=n_steps, step=step,
                                        n_out_frames=n_out, only=[keyword])
            assert res is not None
            bits, labels = res
            hit = _expected_steps(words, keyword, fps=db.fps, step=step, n_out=n_out)
            assert hit, f"{keyword!r} should occur in {transcript}"
            assert {i for i, lab in enumerate(labels) if lab is not None} == hit
            for i in range(n_steps):
                np.testing.assert_array_equal(bits[i], sub.mask if i in hit else full)
            # a word that straddles a step boundary marks both steps
            for s, e, text in zip(words.start_s, words.end_s, words.text):
                if keyword in text.split():
                    a, b = math.floor(s * db.fps), math.ceil(e * db.fps) - 1
                    if a // step != b // step:
                        split_seen = True
                        assert labels[a // step] == keyword and labels[b // step] == keyword
        assert split_seen, "no step size put a step boundary inside the keyword"
        # passing the Words object gives the same as passing the path
        again = kw.keyword_step_masks(db, words, n_steps=-(-n_out // 8), step=8, n_out_frames=n_out, only=[keyword])
        ref = kw.keyword_step_masks(db, data_dir / transcript, n_steps=-(-n_out // 8), step=8, n_out_frames=n_out,
                                    only=[keyword])
        np.testing.assert_array_equal(again[0], ref[0])
        assert again[1] == ref[1]


def test_synthesis_takes_keyword_steps_from_the_subdatabase(keyword_db, scott_dir):
    """End to end through Searcher: every keyword step's window starts and ends inside the keyword's stretches."""
    from gesturedb.io import read_audio
    from gesturedb.synth import Searcher

    samples, sr = read_audio(scott_dir / "inputs" / "2_scott_0_2_2.wav", sr=16000)
    words = read_transcript(scott_dir / "inputs" / "2_scott_0_2_2.TextGrid")
    cut_s = 25.0  # enough for two "time"s, short enough to stay fast
    with gesturedb.open(keyword_db) as db:
        res = Searcher(db).synthesize(samples[: int(cut_s * sr)], sr=sr, transcript=words.between(0, cut_s), step=8)
        bits = {k: masks.unpack_bits(v.mask, db.n_frames) for k, v in kw.subdatabases(db).items()}
        expect = kw.keyword_step_masks(db, words.between(0, cut_s), n_steps=len(res.steps), step=8,
                                       n_out_frames=res.n_frames)[1]
    labels = [st["keyword"] for st in res.steps]
    assert labels == expect and sum(lab is not None for lab in labels) >= 2
    for st in res.steps:
        if st["keyword"]:
            g, n = st["db_frame"], st["out_end"] - st["out_start"]
            assert bits[st["keyword"]][g] and bits[st["keyword"]][g + n - 1], st


def test_step_masks_of_control_and_keywords_keep_each_distinct_row_once(keyword_db, scott_dir):
    """What a synthesis searches under a schedule and keywords: a StepBitsets with one row
    per distinct (control, keyword) pair, equal step by step to the AND of the arrays."""
    from gesturedb import control
    from gesturedb.synth import Searcher

    words = read_transcript(scott_dir / "inputs" / "2_scott_0_2_2.TextGrid")
    T, step = 900, 8
    S = -(-T // step)
    sched = "0-20: left_wrist_high; 20-40: symmetric; 40-: not left_wrist_high"
    with gesturedb.open(keyword_db) as db:
        allowed, labels, kbits = Searcher(db)._step_masks(sched, words, True, n_steps=S, step=step, T=T)
        ctl = control.schedule_bitsets(sched, controls=db.controls, named=db.masks, n_steps=S, step=step,
                                       fps=db.fps, n_out_frames=T, n_frames=db.n_frames)
        kb, klab = kw.keyword_step_masks(db, words, n_steps=S, step=step, n_out_frames=T)
    assert isinstance(allowed, control.StepBitsets) and isinstance(kbits, control.StepBitsets)
    assert allowed.shape == ctl.bitsets.shape == (S, masks.n_words(db.n_frames))
    # 3 schedule rows x (every frame, 'time', 'like'), of which the transcript uses a few
    assert allowed.rows.shape[0] <= 9 and len({(c, k) for c, k in zip(ctl.labels, klab)}) == allowed.rows.shape[0]
    np.testing.assert_array_equal(np.asarray(allowed), ctl.bitsets & kb)
    np.testing.assert_array_equal(np.asarray(kbits), kb)
    assert [lab[0] if lab else None for lab in labels] == ctl.labels
    assert [lab[1] if lab else None for lab in labels] == klab and any(klab)


def test_add_show_remove_drop_real(db_copy):
    with gesturedb.open(db_copy) as db:
        words = db.words
        rows = kw.list_words(db, top=10)
        n_frames, fps = db.n_frames, db.fps
        rec = db.recordings[0]
        preview = kw.show(db, "time")
    assert rows[0].count >= rows[-1].count
    idx = [i for i, t in enumerate(words.text) if t == "time"]
    assert len(idx) >= 2 and len(preview) == len(idx)
    sub = kw.add_keyword(db_copy, "Time", before_s=0.5, after_s=1.0)
    np.testing.assert_array_equal(sub.word_index, idx)
    with gesturedb.open(db_copy) as db:
        got = kw.subdatabases(db)["time"]
        occ = kw.show(db, "time")
        # the new group does not disturb anything else
        assert db.n_frames == n_frames and len(db.words) == len(words)
    for k, wi in enumerate(idx):
        s, e = words.start_s[wi], words.end_s[wi]
        frames = _brute_frames(_frac(s) - Fraction(1, 2), _frac(e) + 1, fps, rec.n_frames)
        assert set(range(int(got.start[k]), int(got.start[k] + got.length[k]))) == {rec.start_frame + f for f in frames}
        assert occ[k].recording == rec.name and occ[k].time_s == pytest.approx(s)
        assert "[time]" in occ[k].context
        # three words on each side of the keyword, from the same recording
        ctx = occ[k].context.replace("... ", "").replace(" ...", "").split()
        lo, hi = max(0, wi - 3), min(len(words), wi + 4)
        assert ctx == [t if j != wi else f"[{t}]" for j, t in enumerate(words.text[lo:hi], start=lo)]
    assert masks.count_bits(got.mask) == len(set().union(*(range(a, a + n) for a, n in zip(got.start, got.length))))

    kw.remove_occurrence(db_copy, "time", 0)
    with gesturedb.open(db_copy) as db:
        after = kw.subdatabases(db)["time"]
    np.testing.assert_array_equal(after.word_index, idx[1:])
    np.testing.assert_array_equal(after.mask, kw._mask_of(after.start, after.length, n_frames))
    kw.drop_keyword(db_copy, "time")
    with gesturedb.open(db_copy) as db:
        assert "time" not in kw.subdatabases(db)


def test_unknown_word_real(db_copy):
    sha = _sha(db_copy)
    with pytest.raises(ParameterError,
                       match=r"keyword 'tiem': not among the \d+ words of .*scott\.h5; close words: .*'time'"):
        kw.add_keyword(db_copy, "tiem")
    with pytest.raises(ParameterError, match=r"keyword 'tiem': no such sub-database|keyword 'tiem': .* has no keyword"):
        kw.drop_keyword(db_copy, "tiem")
    assert _sha(db_copy) == sha


def test_failed_edit_leaves_file_byte_identical(db_copy, monkeypatch):
    kw.add_keyword(db_copy, "good")
    sha = _sha(db_copy)
    listing = sorted(os.listdir(os.path.dirname(db_copy)))
    real = kw._write_subdb

    def write_then_fail(h5, sub):
        real(h5, sub)  # the copy is really changed before the failure
        raise KeyboardInterrupt

    monkeypatch.setattr(kw, "_write_subdb", write_then_fail)
    with pytest.raises(KeyboardInterrupt):
        kw.add_keyword(db_copy, "time")
    with pytest.raises(KeyboardInterrupt):
        kw.remove_occurrence(db_copy, "good", 0)
    monkeypatch.undo()

    # a failure inside drop (after the group was deleted in the copy)
    import h5py

    real_del = h5py.Group.__delitem__

    def del_then_fail(self, name):
        real_del(self, name)
        raise OSError("disk full")

    monkeypatch.setattr(h5py.Group, "__delitem__", del_then_fail)
    with pytest.raises(OSError, match="disk full"):
        kw.drop_keyword(db_copy, "good")
    monkeypatch.undo()
    assert _sha(db_copy) == sha
    assert sorted(os.listdir(os.path.dirname(db_copy))) == listing  # no temporary file left
    # refused edits never touch the file either
    with pytest.raises(ParameterError, match="already has its sub-database"):
        kw.add_keyword(db_copy, "good")
    with pytest.raises(ParameterError, match=r"index: expected an occurrence"):
        kw.remove_occurrence(db_copy, "good", 99)
    assert _sha(db_copy) == sha


def test_export_real(db_copy, tmp_path):
    from gesturedb.db.edit import edit
    from gesturedb.features import rhythm, style

    kw.add_keyword(db_copy, "time", before_s=0.5, after_s=1.0)
    kw.add_keyword(db_copy, "like", before_s=0.3, after_s=0.6)
    with gesturedb.open(db_copy) as db:
        F = db.n_frames
    mine = np.random.default_rng(1).random(F) < 0.5  # a curator's saved mask that is no percentile
    with edit(db_copy) as h5:
        ds = h5[schema.MASKS_GROUP].create_dataset("mine", data=masks.pack_bits(mine))
        ds.attrs["definition"] = "hand-picked"
    out = tmp_path / "time.h5"
    sha = _sha(db_copy)
    with export_keyword(db_copy, "time", out) as ex, gesturedb.open(db_copy) as src:
        sub = kw.subdatabases(src)["time"]
        n = len(sub)
        assert len(ex.recordings) == n and ex.n_frames == int(sub.length.sum())
        assert ex.fps == src.fps and ex.config == src.config and ex.feature_joints == src.feature_joints
        assert ex.motion_timescale_s == src.motion_timescale_s is not None
        frames = np.concatenate([np.arange(a, a + L) for a, L in zip(sub.start, sub.length)])
        for name in ("pose_features", "audio_features", "audio_deltas", "joint_positions", "local_rotations",
                     "root_positions"):
            np.testing.assert_array_equal(getattr(ex, name), getattr(src, name)[frames], err_msg=name)
        # the stored pose mean is the exported frames' own, not the source's
        assert np.array_equal(ex.frame_mean("pose_features"), src.pose_features[frames].mean(axis=0, dtype=np.float64))
        assert sorted(ex.controls) == sorted(src.controls)
        for k in src.controls:
            np.testing.assert_array_equal(ex.controls[k], src.controls[k][frames])
            assert ex.control_units[k] == src.control_units[k]
        np.testing.assert_array_equal(ex.audio_mean, src.audio_mean)
        np.testing.assert_array_equal(ex.audio_std, src.audio_std)
        assert ex.joint_names == src.joint_names
        np.testing.assert_array_equal(ex.skeleton.offsets, src.skeleton.offsets)
        src_rec = src.recordings[0]
        for i, r in enumerate(ex.recordings):
            a = int(sub.start[i]) - src_rec.start_frame
            assert r.name == f"{src_rec.name}@{a / src.fps:.3f}"
            assert r.n_frames == sub.length[i] and r.speaker == src_rec.speaker
            assert r.motion_path == src_rec.motion_path and r.source_fps == src_rec.source_fps
            np.testing.assert_array_equal(ex.frame_recording[r.start_frame:r.stop_frame], i)
            # the exported stretch, exported again as a BVH-able motion, is the source stretch
            m = ex.motion(r.name)
            np.testing.assert_allclose(m.rotations, src.local_rotations[sub.start[i]:sub.start[i] + sub.length[i]])
        # chunks: one per occurrence; clips tile every recording
        np.testing.assert_array_equal(ex.chunks.start, [r.start_frame for r in ex.recordings])
        np.testing.assert_array_equal(ex.chunks.length, sub.length)
        for i, r in enumerate(ex.recordings):
            sel = ex.clips.recording == i
            st, ln = ex.clips.start[sel], ex.clips.length[sel]
            assert st[0] == r.start_frame and st[-1] + ln[-1] == r.stop_frame and np.all(st[1:] == st[:-1] + ln[:-1])
        # words: those starting in the stretch, relative to it; the keyword where the sub-database says
        exsub = kw.subdatabases(ex)["time"]
        assert set(kw.subdatabases(ex)) == {"time"}
        for i, r in enumerate(ex.recordings):
            wi = int(exsub.word_index[i])
            assert ex.words.text[wi] == "time" and ex.words.recording[wi] == i
            swi = int(sub.word_index[i])
            stretch_s = (sub.start[i] - src_rec.start_frame) / src.fps
            assert ex.words.start_s[wi] == pytest.approx(src.words.start_s[swi] - stretch_s)
            sel = ex.words.recording == i
            assert np.all(ex.words.start_s[sel] >= 0) and np.all(ex.words.end_s[sel] <= r.duration_s + 1e-9)
        np.testing.assert_array_equal(exsub.start, [r.start_frame for r in ex.recordings])
        np.testing.assert_array_equal(exsub.mask, masks.full_mask(ex.n_frames))
        assert exsub.definition["exported_from"]["database"] == os.path.abspath(db_copy)
        # default percentile masks are recomputed over the exported frames
        assert set(ex.masks) == set(src.masks)
        name = next(k for k, d in ex.mask_definitions.items() if "p85" in d)
        res = masks.compile_mask(ex.mask_definitions[name], controls=ex.controls)
        np.testing.assert_array_equal(ex.masks[name], res.words)
        np.testing.assert_array_equal(masks.unpack_bits(ex.masks["mine"], ex.n_frames), mine[frames])
        assert ex.mask_definitions["mine"] == "hand-picked"
        # clip signatures are measured at the clip's place in the source recording
        pos = np.asarray(src.joint_positions[src_rec.start_frame:src_rec.stop_frame], dtype=np.float64)
        names = {n: j for j, n in enumerate(src.joint_names)}
        joints = {role: names[n] for role, n in src.feature_joints.items()}
        speed = rhythm.hand_speed(pos, joints=joints, fps=src.fps)
        for c in range(len(ex.clips)):
            r = ex.recordings[int(ex.clips.recording[c])]
            at = int(sub.start[r.index]) - src_rec.start_frame + int(ex.clips.start[c]) - r.start_frame
            L = int(ex.clips.length[c])
            np.testing.assert_allclose(
                ex.clips.style[c], style.style_signatures(pos, joints=joints, fps=src.fps, starts=[at], lengths=[L])[0])
            assert ex.clips.rhythm_motion[c] == rhythm.motion_rhythm(speed, start=at, length=L, fps=src.fps)
            ws, we = int(ex.clips.word_start[c]), int(ex.clips.word_end[c])
            assert np.all(ex.words.recording[ws:we] == r.index)
            t0 = (int(ex.clips.start[c]) - r.start_frame) / ex.fps
            assert ex.clips.rhythm_audio[c] == rhythm.audio_rhythm(ex.words.start_s[ws:we], start_s=t0,
                                                                   end_s=t0 + L / ex.fps)
        # `gesturedb info` works on it
        s = _cli_module("info").summary(ex)
        assert s["frames"] == ex.n_frames and len(s["recordings"]) == n
    assert _sha(db_copy) == sha  # the source is not modified

    # fixed chunks within each occurrence
    with export_keyword(db_copy, "like", tmp_path / "like.h5", chunk_frames=8) as ex:
        for i, r in enumerate(ex.recordings):
            sel = ex.chunks.recording == i
            assert ex.chunks.start[sel][0] == r.start_frame
            assert np.all(ex.chunks.length[sel][:-1] == 8) and ex.chunks.length[sel].sum() == r.n_frames
    with pytest.raises(ParameterError, match=r"output: .* is the source database"):
        export_keyword(db_copy, "time", db_copy)
    with pytest.raises(ParameterError, match=r"keyword 'hand': no such sub-database .*keywords: like, time"):
        export_keyword(db_copy, "hand", tmp_path / "hand.h5")
    assert not (tmp_path / "hand.h5").exists()


def test_cli_keywords(db_copy, tmp_path, capsys):
    rc, out = _cli([str(db_copy), "list", "--top", "5"], capsys)
    assert rc == 0 and "no keyword sub-databases" in out and "most frequent" in out
    rc, out = _cli([str(db_copy), "show", "good"], capsys)
    assert rc == 0 and "no sub-database yet" in out and "[good]" in out
    rc, out = _cli([str(db_copy), "add", "good", "--before", "0.25", "--after", "0.75"], capsys)
    assert rc == 0 and "'good'" in out
    with gesturedb.open(db_copy) as db:
        sub = kw.subdatabases(db)["good"]
    assert (sub.before_s, sub.after_s) == (0.25, 0.75)
    rc, out = _cli([str(db_copy), "list", "--top", "1000"], capsys)
    assert "1 keyword sub-database(s)" in out and "*good" in out
    rc, out = _cli([str(db_copy), "show", "good"], capsys)
    assert out.splitlines()[0].startswith("sub-database good") and len(out.splitlines()) == 1 + len(sub)
    with pytest.raises(GestureDBError, match="already has its sub-database"):
        _cli([str(db_copy), "add", "good"], capsys)
    _cli([str(db_copy), "add", "good", "--replace"], capsys)
    rc, out = _cli([str(db_copy), "export", "good", "-o", str(tmp_path / "good.h5")], capsys)
    assert rc == 0 and f"{len(sub)} recording(s)" in out
    rc, out = _cli([str(db_copy), "remove", "good", "0"], capsys)
    assert rc == 0 and f"{len(sub) - 1} left" in out
    rc, out = _cli([str(db_copy), "drop", "good"], capsys)
    assert rc == 0 and "dropped 'good'" in out
