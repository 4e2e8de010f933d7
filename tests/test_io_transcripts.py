"""Transcript readers: real TextGrids and GENEA TSVs, JSON, normalisation, validation."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io import Words, read_transcript
from gesturedb.io.transcripts import normalize_word, read_genea_tsv, read_textgrid


def _raw_textgrid_words(path):
    """(xmin, xmax, text) of the non-empty intervals of the first tier, by plain regex."""
    text = path.read_text()
    first_tier = text.split("item [2]")[0]
    rows = re.findall(r'xmin = ([\d.]+)\s*\n\s*xmax = ([\d.]+)\s*\n\s*text = "(.*)"', first_tier)
    return [(float(a), float(b), t) for a, b, t in rows if t.strip()]


def test_beat2_textgrid_words(scott_dir):
    path = scott_dir / "2_scott_0_1_1.TextGrid"
    w = read_transcript(path)
    assert len(w) == 199 and w.source == str(path)
    raw = _raw_textgrid_words(path)
    assert len(raw) == 199
    np.testing.assert_allclose(w.start_s, [r[0] for r in raw])
    np.testing.assert_allclose(w.end_s, [r[1] for r in raw])
    assert w.text == [r[2].lower() for r in raw]
    assert w.text[:3] == ["the", "first", "thing"] and w.start_s[0] == 1.42
    assert np.all(np.diff(w.onsets) >= 0) and np.all(w.end_s >= w.start_s)
    assert w.end_s[-1] <= 64.1


@pytest.mark.parametrize("name", ["2_scott_0_2_2", "2_scott_0_3_3", "2_scott_0_4_4"])
def test_input_textgrids_keep_apostrophes(scott_dir, name):
    w = read_transcript(scott_dir / "inputs" / f"{name}.TextGrid")
    assert len(w) > 150
    assert all(re.fullmatch(r"[a-z0-9']+", t) for t in w.text)
    assert any("'" in t for t in w.text)  # "i'm", "you're" stay whole


def test_genea_tsv_files(data_dir):
    files = sorted((data_dir / "genea2023-transcripts").glob("*.tsv"))
    assert len(files) == 4
    for path in files:
        lines = [ln.split("\t") for ln in path.read_text().splitlines() if ln.strip()]
        # independent count: lines whose word has any letter or digit survive
        keep = [ln for ln in lines if re.search(r"[A-Za-z0-9]", ln[2])]
        w = read_transcript(path)
        assert len(w) == len(keep), path.name
        np.testing.assert_allclose(w.start_s, [float(ln[0]) for ln in keep])
        assert all(t == t.lower() and not re.search(r"[^\w\s']", t) for t in w.text)
    w = read_genea_tsv(data_dir / "genea2023-transcripts" / "trn_2023_v0_057_main-agent.tsv")
    assert w.text[0] == "um" and w.start_s[0] == 1.24  # "um." with its full stop removed
    assert "there is" in w.text  # one interval, two words: kept as one entry


def test_textgrid_tier_lookup_is_case_insensitive_and_lists_tiers(tmp_path):
    tg = """File type = "ooTextFile"
Object class = "TextGrid"

xmin = 0
xmax = 3
tiers? <exists>
size = 2
item []:
    item [1]:
        class = "IntervalTier"
        name = "Words"
        xmin = 0
        xmax = 3
        intervals: size = 4
        intervals [1]:
            xmin = 0
            xmax = 0.5
            text = ""
        intervals [2]:
            xmin = 0.5
            xmax = 1.2
            text = "Hello,"
        intervals [3]:
            xmin = 1.2
            xmax = 2.0
            text = "<sil>"
        intervals [4]:
            xmin = 2.0
            xmax = 3
            text = "WORLD!"
    item [2]:
        class = "TextTier"
        name = "beats"
        xmin = 0
        xmax = 3
        points: size = 1
        points [1]:
            number = 1.0
            mark = "b"
"""
    path = tmp_path / "case.TextGrid"
    path.write_text(tg)
    w = read_transcript(path)
    assert w.text == ["hello", "world"] and w.start_s.tolist() == [0.5, 2.0]
    with pytest.raises(InputFileError, match=r"no tier named 'phones' \(case-insensitive\); tiers: 'Words', 'beats'"):
        read_textgrid(path, tier="phones")
    with pytest.raises(InputFileError, match="tier 'beats': expected an interval tier"):
        read_textgrid(path, tier="BEATS")
    bad = tmp_path / "bad.TextGrid"
    bad.write_text("this is not a textgrid\n")
    with pytest.raises(InputFileError, match=r"bad.TextGrid: line 1: expected the Praat header 'File type = "
                                             r"\"ooTextFile\"' \(a TextGrid saved as text\); got 'this is not"):
        read_textgrid(bad)
    bad.write_text("")
    with pytest.raises(InputFileError, match="bad.TextGrid: empty file; expected a Praat TextGrid"):
        read_textgrid(bad)
    # Praat saves non-ASCII text as UTF-16 with a byte-order mark: read, and its errors named by line too
    u16 = tmp_path / "u16.TextGrid"
    u16.write_text(tg.replace("Hello,", "Héllo,"), encoding="utf-16")
    assert read_transcript(u16).text == ["héllo", "world"]
    u16.write_text(tg.replace("xmax = 3", "xmax = soon", 1), encoding="utf-16")
    with pytest.raises(InputFileError, match=r"u16.TextGrid: line \d+: xmax: expected a number of seconds, got 'soon'"):
        read_textgrid(u16)


def test_json_layouts(tmp_path):
    items = [{"start": 0.1, "end": 0.4, "word": "Hi!"}, {"start_s": 0.5, "end_s": 0.9, "text": "there"},
             {"start": "1.0", "end": 1.2, "word": ""}]
    a = tmp_path / "a.json"
    a.write_text(json.dumps({"words": items}))
    b = tmp_path / "b.JSON"
    b.write_text(json.dumps(items))
    for path in (a, b):
        w = read_transcript(path)
        assert w.text == ["hi", "there"] and w.end_s.tolist() == [0.4, 0.9]


@pytest.mark.parametrize("doc, message", [
    ({"segments": []}, r"expected \{\"words\".*got dict with keys segments"),
    ([{"start": 0, "word": "a"}], r"words\[0\]: missing 'end'"),
    ([{"start": 0, "end": "soon", "word": "a"}], r"words\[0\]: end: expected a number of seconds, got 'soon'"),
    ([{"start": 0, "end": 1, "word": 5}], r"words\[0\]: word: expected a string"),
    ([{"start": 0, "end": 1, "word": "a"}, {"start": 2, "end": 1.5, "word": "b"}],
     r"words\[1\]: word 1 \('b'\): end 1.5 s is before start 2.0 s"),
    ([{"start": 0, "end": None, "word": "a"}], r"words\[0\]: end: expected a number"),
    ([{"start": "nan", "end": 1, "word": "a"}], r"words\[0\]: start: expected a finite number"),
    ([{"start": 0, "end": 1, "word": "a"}, {"start": -3, "end": -2.5, "word": "b"}],
     r"words\[1\]: start: expected a time >= 0 s for word 'b', got -3.0"),
])
def test_json_errors(tmp_path, doc, message):
    path = tmp_path / "w.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match=message):
        read_transcript(path)


def test_json_syntax_error(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text('{"words": [')
    with pytest.raises(InputFileError, match="invalid JSON at line 1"):
        read_transcript(path)


@pytest.mark.parametrize("body, message", [
    ("0\t0.5\thello\n0.4\tx\tworld\n", r"line 2: end: expected a number of seconds, got 'x'"),
    ("0\t0.5\thello\n0.6\n", r"line 2: expected start<TAB>end<TAB>word"),
    ("0\t0.5\thello\n1.0\t0.7\tworld\n", r"line 2: word 1 \('world'\): end 0.7 s is before start 1.0 s"),
    ("1.0\t1.5\thello\n0.6\t0.7\tworld\n", r"line 2: word 1 \('world'\): starts at 0.6 s, before word 0"),
    ("0\t0.5\thello\ninf\t1\tworld\n", r"line 2: start: expected a finite number"),
    ("start\tend\tword\n0\t1\thi\n", None),  # a header naming the columns (pandas, spreadsheets) is skipped
    ("Start_s End_s text\n0 1 hi\n", None),
    ("from\tto\tword\n0\t1\thi\n", r"line 1: start: expected a number of seconds, got 'from'"),
    ("0\t0.5\thi\nstart\tend\tword\n", r"line 2: start: expected a number of seconds, got 'start'"),
    # issue 41: a negative time became a stretch of -58269 frames in `keywords add`
    ("0\t0.5\thello\n-1.5\t-1.2\tworld\n", r"line 2: start: expected a time >= 0 s for word 'world', got -1.5"),
    ("-0.2\t0.5\thello\n", r"line 1: start: expected a time >= 0 s for word 'hello', got -0.2"),
    ("0\t-0.5\thello\n", r"line 1: end: expected a time >= 0 s for word 'hello', got -0.5"),
    ("0\t0.5\thello\nnan\t1\tworld\n", r"line 2: start: expected a finite number"),
    ("-5\t-4\t<sil>\n0\t1\thi\n", None),  # a silence before the start carries no word: skipped as ever
])
def test_tsv_errors_name_the_line(tmp_path, body, message):
    path = tmp_path / "w.tsv"
    path.write_text(body)
    if message is None:
        assert read_transcript(path).text == ["hi"]
        return
    with pytest.raises(InputFileError, match=message) as err:
        read_transcript(path)
    assert str(err.value).startswith(str(path))


_TEXTGRID = """File type = "ooTextFile"
Object class = "TextGrid"

xmin = 0
xmax = 3
tiers? <exists>
size = 1
item []:
    item [1]:
        class = "IntervalTier"
        name = "words"
        xmin = 0
        xmax = 3
        intervals: size = 2
        intervals [1]:
            xmin = {a}
            xmax = {b}
            text = "hello"
        intervals [2]:
            xmin = {b}
            xmax = 3
            text = "world"
"""


@pytest.mark.parametrize("a, b, message", [
    ("-2", "1", r"line 16: xmin: expected a finite time >= 0 s, got '-2'"),
    ("0", "nan", r"line 17: xmax: expected a finite time >= 0 s, got 'nan'"),
    ("2", "1", r"line 17: xmax 1 s is before xmin 2 s \(line 16\)"),
])
def test_textgrid_bad_times_name_the_line(tmp_path, a, b, message):
    path = tmp_path / "w.TextGrid"
    path.write_text(_TEXTGRID.format(a=a, b=b))
    with pytest.raises(InputFileError, match=message) as err:
        read_transcript(path)
    assert str(err.value).startswith(f"{path}: line ") and "\n" not in str(err.value)
    path.write_text(_TEXTGRID.format(a="0.5", b="1"))
    assert read_transcript(path).start_s.tolist() == [0.5, 1.0]


def test_unknown_extension(tmp_path):
    with pytest.raises(InputFileError, match=r"unknown transcript extension '.srt'; expected .TextGrid, .tsv or .json"):
        read_transcript(tmp_path / "x.srt")


def test_normalize_word():
    cases = {"Yeah,": "yeah", "It is-": "it is", "Don't": "don't", "<sil>": "", "sp": "", "SIL": "",
             "(?)": "", "###": "", "value-.": "value", "\u2019tis": "tis", "rock'n'roll": "rock'n'roll",
             "  Two   words ": "two words", "Café": "café"}
    for raw, want in cases.items():
        assert normalize_word(raw) == want, raw


def test_words_container():
    w = Words(np.array([0.0, 0.5, 1.0, 2.0]), np.array([0.4, 0.9, 1.5, 2.5]), ["a", "b", "c", "d"], "x.tsv")
    assert len(w) == 4 and w.onsets is w.start_s
    assert w[1:3].text == ["b", "c"] and w[1:3].source == "x.tsv"
    assert w[-1].text == ["d"]
    assert w[np.array([True, False, False, True])].text == ["a", "d"]
    assert w[np.array([0, 2])].text == ["a", "c"]
    with pytest.raises(ParameterError, match="expected non-decreasing start times"):
        w[np.array([2, 0])]  # words stay in time order
    assert w.between(0.5, 2.0).text == ["b", "c"]
    assert list(w)[0] == (0.0, 0.4, "a")
    with pytest.raises(IndexError):
        w[4]
    with pytest.raises(ParameterError, match=r"word 1 \('b'\): end 0.3 s is before start 0.5 s"):
        Words(np.array([0.0, 0.5]), np.array([0.4, 0.3]), ["a", "b"])
    with pytest.raises(ParameterError, match="one entry per word"):
        Words(np.array([0.0]), np.array([0.4, 0.3]), ["a", "b"])
    empty = Words(np.zeros(0), np.zeros(0), [])
    assert len(empty) == 0 and len(empty.between(0, 10)) == 0


# --- does a transcript fit its audio ------------------------------------------------------

def test_declared_length_comes_from_the_textgrid_and_selections_drop_it(scott_dir, data_dir):
    import soundfile as sf

    for tg in [scott_dir / "2_scott_0_1_1.TextGrid", *sorted((scott_dir / "inputs").glob("*.TextGrid"))]:
        w = read_transcript(tg)
        # the aligner wrote the length of the audio it was given
        assert abs(w.duration_s - sf.info(tg.with_suffix(".wav")).duration) < 1e-3, tg
        assert w.accept_mismatch is False
    assert read_transcript(data_dir / "genea2023-transcripts/trn_2023_v0_000_main-agent.tsv").duration_s is None
    w = read_transcript(scott_dir / "2_scott_0_1_1.TextGrid", accept_mismatch=True)
    for part in (w[:10], w[w.start_s < 5], w.between(0, 5), w[3]):
        assert part.duration_s is None and part.accept_mismatch is True


def test_check_words_fit_tolerance_and_acceptance():
    import warnings

    from gesturedb.errors import GestureDBWarning
    from gesturedb.io.transcripts import FIT_TOLERANCE_S, check_words_fit

    w = Words([0.5, 9.0, 9.9 + FIT_TOLERANCE_S], [1.0, 9.5, 11.0], ["a", "b", "c"], source="t.tsv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_words_fit(w, 9.9)  # the last word starts within the tolerance, ends past the audio: fits
    with pytest.raises(InputFileError, match=r"^t.tsv: does not fit the audio \(s.wav\): the transcript ends at "
                                             r"11.00 s, the audio is 9.70 s long: 1 of 3 words start more than 0.1 s "
                                             r"after its end\. A transcript of another recording\? To use it anyway "
                                             r"pass --accept-transcript-mismatch \(accept_mismatch=True\)$"):
        check_words_fit(w, 9.7, audio="s.wav")
    with pytest.warns(GestureDBWarning, match=r"t.tsv: does not fit the audio: .* \(accepted; words that start"):
        check_words_fit(w, 9.7, accept_mismatch=True)
    # a declared length that differs: refused even with every word inside
    tg = Words(w.start_s, w.end_s, w.text, source="t.TextGrid", duration_s=12.0)
    check_words_fit(tg, 12.0 - FIT_TOLERANCE_S / 2)
    with pytest.raises(InputFileError, match=r"the transcript was made for 12.00 s of speech \(its xmax\), the audio "
                                             r"is 20.00 s long\. A transcript"):
        check_words_fit(tg, 20.0)
    with pytest.warns(GestureDBWarning, match=r"made for 12.00 s .* \(accepted\)$"):
        check_words_fit(Words(w.start_s, w.end_s, w.text, duration_s=12.0, accept_mismatch=True), 20.0)
    # no word inside the audio: nothing to use, refused even when accepted
    with pytest.raises(InputFileError, match="expected words inside the audio"):
        check_words_fit(w, 0.4, accept_mismatch=True)
