"""What a new user meets in the first hour: help-text examples that work, listings that show what the
README promises, one pairing report per failed build, and speech whose transcript does not fit."""
from __future__ import annotations

import argparse
import json
import re
import shutil
import warnings

import pytest
import soundfile as sf

import gesturedb
from gesturedb import control
from gesturedb.cli.main import main, make_parser
from gesturedb.errors import GestureDBWarning, InputFileError
from gesturedb.io.joints import BODY_ROLES, FEATURE_ROLES


def _texts(parser, path=("gesturedb",)):
    """(command path, option dest or None, text) of every description, epilog and help in the CLI."""
    for t in (parser.description, parser.epilog):
        if t:
            yield path, None, t
    for a in parser._actions:
        if a.help and a.help is not argparse.SUPPRESS:
            yield path, a.dest, a.help
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in a.choices.items():
                yield from _texts(sp, path + (name,))


def _examples():
    """Every quoted example in the help texts: ``e.g. 'EXAMPLE'`` or ``e.g. "EXAMPLE"``."""
    out = []
    for path, dest, text in _texts(make_parser()):
        for m in re.finditer(r"e\.g\. (['\"])(.+?)\1(?=[\s,;.)]|$)", text):
            out.append((" ".join(path), dest, m.group(2)))
    return out


def test_every_help_example_works(scott_db):
    examples = _examples()
    checked = []
    for where, dest, ex in examples:
        if where == "gesturedb masks" and dest is None:
            # a mask expression: compiles on a real database (built-in names, saved percentile masks)
            res = control.compile_mask(ex, controls=scott_db.controls, named=scott_db.masks)
            assert 0 < control.count_bits(res.words) < scott_db.n_frames, ex
        elif where == "gesturedb synth" and dest == "control":
            sb = control.schedule_bitsets(ex, controls=scott_db.controls, named=scott_db.masks,
                                          n_out_frames=int(30 * scott_db.fps), fps=scott_db.fps)
            assert len(sb.bitsets) > 0
        elif where == "gesturedb build" and dest == "joint_map":
            mapping = json.loads(ex)
            assert set(mapping) <= set(FEATURE_ROLES + BODY_ROLES), ex
        else:
            pytest.fail(f"help example of `{where}` ({dest}) is not checked by this test: {ex!r}")
        checked.append(ex)
    assert len(checked) >= 3


def test_masks_help_shows_a_working_example(capsys):
    with pytest.raises(SystemExit):
        main(["masks", "--help"])
    out = capsys.readouterr().out
    assert "'left_wrist_height > p85 and not left_wrist_fast'" in " ".join(out.split())
    assert "not fast'" not in out


def test_masks_list_shows_the_built_in_names(scott_db_path, capsys):
    assert main(["masks", str(scott_db_path), "list"]) == 0
    out = capsys.readouterr().out
    section = out.split("built-in names")[1].split("masks in the database")[0]
    rows = [ln.split() for ln in section.strip().splitlines()[1:]]
    assert [r[0] for r in rows] == list(control.DEFAULT_NAMED)
    with gesturedb.open(scott_db_path) as db:
        for r in rows:
            n = control.count_bits(control.compile_mask(r[0], controls=db.controls, named=db.masks).words)
            assert r[1] == f"{100 * n / db.n_frames:.1f}%"  # the share of frames the name allows
            assert " ".join(r[2:]) == control.DEFAULT_NAMED[r[0]]
    assert "left_wrist_height_high" in out.split("masks in the database")[1]


def test_info_without_a_database_and_with_keywords(scott_db_path, tmp_path, capsys):
    assert main(["info", "--schema"]) == 0
    assert "Schema version" in capsys.readouterr().out
    assert main(["info"]) == 2
    assert "expected a database to summarise (or --schema" in capsys.readouterr().err
    db = tmp_path / "kw.h5"
    shutil.copy(scott_db_path, db)
    assert main(["info", str(db)]) == 0
    out = capsys.readouterr().out
    assert re.search(r"keywords\s+none \(gesturedb keywords .*kw.h5 add WORD", out)
    assert main(["keywords", str(db), "add", "time"]) == 0
    capsys.readouterr()
    assert main(["info", str(db)]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.strip().startswith("keywords"))
    with gesturedb.open(db) as d:
        from gesturedb.db.keywords import subdatabases

        n = len(subdatabases(d)["time"])
    assert f"1 keyword sub-database(s): time ({n} x," in line
    assert main(["info", str(db), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["keywords"]["time"]["occurrences"] == n


def test_failed_build_prints_its_pairing_report_once(scott_dir, tmp_path, capsys):
    d = tmp_path / "only_audio"
    d.mkdir()
    shutil.copy(scott_dir / "inputs/2_scott_0_5_5.wav", d / "a.wav")
    (d / "notes.xyz").write_text("x")
    assert main(["build", str(d), "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert err.count("skipped 2 file(s)") == 1 and err.count("a.wav: no motion file") == 1
    assert err.startswith("gesturedb build: error: inputs: expected at least one recording")


# --- transcripts that do not fit the speech ------------------------------------------------

@pytest.fixture()
def short_speech(scott_dir, tmp_path):
    """20 s of the recording's speech, and its whole 63.5 s transcript."""
    y, sr = sf.read(scott_dir / "2_scott_0_1_1.wav", dtype="float32")
    wav = tmp_path / "short.wav"
    sf.write(wav, y[: 20 * sr], sr, subtype="FLOAT")
    return wav, scott_dir / "2_scott_0_1_1.TextGrid"


def test_transcript_longer_than_the_audio_is_refused_unless_accepted(scott_db, short_speech, tmp_path, capsys):
    from gesturedb.io import read_transcript
    from gesturedb.io.transcripts import FIT_TOLERANCE_S
    from gesturedb.synth import Searcher
    from gesturedb.synth.graph import GraphSynthesizer

    wav, tg = short_speech
    w = read_transcript(tg)
    late = int((w.start_s > 20.0 + FIT_TOLERANCE_S).sum())
    msg = (rf"2_scott_0_1_1.TextGrid: does not fit the audio \(.*short.wav\): the transcript ends at "
           rf"{w.end_s.max():.2f} s, the audio is 20.00 s long: {late} of 199 words start more than 0.1 s after its "
           r"end; the transcript was made for 64.10 s of speech \(its xmax\), the audio is 20.00 s long")
    with pytest.raises(InputFileError, match=msg + r"\. A transcript of another recording\? To use it anyway pass "
                                               r"--accept-transcript-mismatch \(accept_mismatch=True\)"):
        Searcher(scott_db).synthesize(wav, transcript=tg)
    with pytest.raises(InputFileError, match="does not fit the audio"):
        GraphSynthesizer(scott_db).synthesize(wav, transcript=tg)
    # said so: a warning, and the words inside the audio drive the keyword steps
    with pytest.warns(GestureDBWarning, match=msg + r" \(accepted; words that start after the audio's end are "
                                                  r"ignored\)"):
        Searcher(scott_db).synthesize(wav, transcript=read_transcript(tg, accept_mismatch=True))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # its own words (a selection: no declared length) fit: no warning
        Searcher(scott_db).synthesize(wav, transcript=_words_until(tg, 20.0))
    # the command line refuses it, names the flag, and writes nothing
    out = tmp_path / "o.bvh"
    args = ["synth", str(scott_db.path), "--audio", str(wav), "--transcript", str(tg), "-o", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "does not fit the audio" in err and "--accept-transcript-mismatch" in err and not out.exists()
    # with the flag it says so in one line and synthesizes
    assert main(args + ["--accept-transcript-mismatch"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gesturedb synth: warning: ") and "audio is 20.00 s long" in err[0]
    assert out.exists()


def test_transcript_of_a_shorter_recording_is_refused(scott_db, scott_dir, capsys, tmp_path):
    """Every word of another, shorter take lies inside the audio: its TextGrid's declared length gives it away."""
    from gesturedb.synth import Searcher

    wav, tg = scott_dir / "inputs/2_scott_0_3_3.wav", scott_dir / "inputs/2_scott_0_2_2.TextGrid"
    with pytest.raises(InputFileError, match=r"2_scott_0_2_2.TextGrid: does not fit the audio \(.*2_scott_0_3_3.wav\):"
                                             r" the transcript was made for 62.00 s of speech \(its xmax\), the audio "
                                             r"is 68.00 s long\. A transcript of another recording\?"):
        Searcher(scott_db).synthesize(wav, transcript=tg)


def _words_until(tg, end_s):
    from gesturedb.io import read_transcript

    w = read_transcript(tg)
    return w[w.end_s <= end_s]


def test_transcript_with_no_word_inside_the_audio_is_an_error(scott_db, short_speech, tmp_path, capsys):
    from gesturedb.io import read_transcript
    from gesturedb.io.transcripts import Words
    from gesturedb.synth import Searcher
    from gesturedb.synth.graph import GraphSynthesizer

    wav, tg = short_speech
    w = read_transcript(tg)
    late = Words(w.start_s + 30.0, w.end_s + 30.0, w.text, source=str(tg))
    with pytest.raises(InputFileError, match=r"TextGrid: words: expected words inside the audio \(.*short.wav\), "
                                             r"which lasts 20.00 s; got 199 words from 3\d\.\d\d to 9\d\.\d\d s"):
        Searcher(scott_db).synthesize(wav, transcript=late)
    with pytest.raises(InputFileError, match="expected words inside the audio"):
        GraphSynthesizer(scott_db).synthesize(wav, transcript=late)
    # nothing is written by the command line
    tsv = tmp_path / "late.tsv"
    tsv.write_text("".join(f"{s:.2f}\t{e:.2f}\t{t}\n" for s, e, t in late))
    assert main(["synth", str(scott_db.path), "--audio", str(wav), "--transcript", str(tsv),
                 "-o", str(tmp_path / "o.bvh")]) == 2
    assert "expected words inside the audio" in capsys.readouterr().err
    assert not (tmp_path / "o.bvh").exists()
