"""`gesturedb eval controls|motion` and `gesturedb render` end to end on the real recording, small settings."""
from __future__ import annotations

import argparse
import json
import re

import numpy as np
import pytest

import gesturedb
from gesturedb.errors import InputFileError, ParameterError


@pytest.fixture(scope="module")
def parser():
    from gesturedb.cli import eval as cli_eval
    from gesturedb.cli import render as cli_render

    p = argparse.ArgumentParser(prog="gesturedb")
    sub = p.add_subparsers(dest="command", required=True)
    cli_eval.add_parser(sub)
    cli_render.add_parser(sub)
    return p


@pytest.fixture()
def run(parser):
    def _run(*argv):
        args = parser.parse_args([str(a) for a in argv])
        return args.run(args)

    return _run


@pytest.fixture(scope="module")
def mirror_db(scott_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("clieval") / "scott_mirror.h5"
    gesturedb.build([scott_dir], out, mirror=True).close()
    return out


def test_eval_controls_writes_table_json_markdown_plot(run, mirror_db, scott_dir, tmp_path, capsys):
    wav = scott_dir / "inputs" / "2_scott_0_3_3.wav"
    rc = run("eval", "controls", mirror_db, "--audio", wav, "--json", tmp_path / "c.json", "--md", tmp_path / "c.md",
             "--plot", tmp_path / "c.png", "--strict")
    out = capsys.readouterr().out
    assert rc == 0, out
    for name in ("wrist high", "wrist low", "wrist fast", "wrist slow", "asymmetric", "symmetric"):
        assert re.search(rf"^{name} .* PASS$", out, re.M), out
    d = json.loads((tmp_path / "c.json").read_text())
    assert [r["control"] for r in d["rows"]][:2] == ["wrist high", "wrist low"] and d["passed"] is True
    high = d["rows"][0]
    assert high["unit"] == "cm" and high["mean"] > high["threshold"] > high["unconstrained_mean"]
    md = (tmp_path / "c.md").read_text()
    assert md.startswith("### Controlled synthesis") and "| wrist slow |" in md
    assert (tmp_path / "c.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_controls_strict_exits_1_on_a_failed_check(run, mirror_db, scott_dir, capsys):
    wav = scott_dir / "inputs" / "2_scott_0_3_3.wav"
    assert run("eval", "controls", mirror_db, "--audio", wav, "--min-std-ratio", "50") == 0
    assert "FAILED:" in capsys.readouterr().out
    assert run("eval", "controls", mirror_db, "--audio", wav, "--min-std-ratio", "50", "--strict") == 1


def test_eval_motion_holdout_report(run, scott_dir, tmp_path, capsys):
    out = tmp_path / "report"
    rc = run("eval", "motion", "--data-dir", scott_dir, "--holdout-start", 48, "--holdout-end", 63.5, "-o", out,
             "--video", "gif", "--video-seconds", 1.0, "--controls", "--systems", "random,ranksum_pose",
             "--starts", 2)
    assert rc == 0
    text = capsys.readouterr().out
    assert "ground truth" in text and "rank-sum, pose pre-selection" in text and "Table 2" in text
    d = json.loads((out / "metrics.json").read_text())
    assert list(d["inputs"][0]["metrics"]) == ["ground_truth", "random", "ranksum_pose"]
    # the search again from 2 random starts, beside the ground truth and the mean start
    assert len(d["inputs"][0]["starts"]["ranksum_pose"]) == 2
    part = text[text.index("from 2 random starting poses"):]
    # one ground-truth row in the table, or in each of its parts where it is wider than a terminal
    starts = [p for p in part.split("\n\n") if "2 random starts" in p]
    assert "H(speed) vs GT" in part and starts and all(p.count("ground truth") == 1 for p in starts)
    assert d["controls"]["rows"][0]["control"] == "wrist high"
    assert (out / "train.h5").is_file()  # kept for `eval controls` or inspection
    html = (out / "index.html").read_text()
    srcs = re.findall(r'src="([^"]+)"', html)
    assert {"sheet_0.png", "video_0.gif", "controls.png", "speed_0.png", "wrist_0.png"} <= set(srcs)
    for s in srcs:
        assert (out / s).stat().st_size > 1000, s
    import imageio.v3 as iio

    assert iio.imread(out / "video_0.gif", index=None).shape[0] == 15  # 1 s at 15 fps
    sheet = iio.imread(out / "sheet_0.png")
    assert sheet.shape[0] == 3 * 300  # ground truth | rank-sum | random, one row each


def test_eval_motion_new_speech(run, mirror_db, scott_dir, tmp_path):
    out = tmp_path / "rep"
    wavs = [scott_dir / "inputs" / "2_scott_0_4_4.wav", scott_dir / "inputs" / "2_scott_0_5_5.wav"]
    rc = run("eval", "motion", mirror_db, "--audio", wavs[0], "--audio", wavs[1], "-o", out, "--no-render", "-q",
             "--systems", "audio_only,ranksum_audio")
    assert rc == 0
    d = json.loads((out / "metrics.json").read_text())
    assert d["mode"] == "inputs" and [i["name"] for i in d["inputs"]] == ["2_scott_0_4_4", "2_scott_0_5_5"]
    assert set(d["summary"]) == {"audio_only", "ranksum_audio"}
    m = [i["metrics"]["ranksum_audio"]["average_jerk_m_s3"] for i in d["inputs"]]
    assert d["summary"]["ranksum_audio"]["average_jerk_m_s3"] == pytest.approx(np.mean(m))
    assert "mean over 2 inputs" in (out / "metrics.txt").read_text()
    assert not (out / "sheet_0.png").exists()


def test_eval_motion_argument_errors(run, mirror_db, scott_dir, tmp_path):
    with pytest.raises(ParameterError, match="expected DB.h5 and at least one --audio"):
        run("eval", "motion", mirror_db, "-o", tmp_path)
    with pytest.raises(ParameterError, match="needs --data-dir, --holdout-start and --holdout-end"):
        run("eval", "motion", "--data-dir", scott_dir, "--holdout-start", 48, "-o", tmp_path)
    with pytest.raises(ParameterError, match="not both"):
        run("eval", "motion", mirror_db, "--audio", "x.wav", "--data-dir", scott_dir, "--holdout-start", 1,
            "--holdout-end", 2, "-o", tmp_path)
    with pytest.raises(ParameterError, match="--systems: expected names"):
        run("eval", "motion", mirror_db, "--audio", "x.wav", "-o", tmp_path, "--systems", "ground_truth")


def test_render_npz_bvh_and_database_stretch(run, mirror_db, tmp_path, capsys):
    import imageio.v3 as iio

    from gesturedb.io import write_bvh

    with gesturedb.open(mirror_db) as db:
        m = db.motion(0, 2.0, 4.0)
        pos = m.positions
        np.savez(tmp_path / "a.npz", positions=pos.astype(np.float32), parents=np.asarray(m.skeleton.parents),
                 fps=15.0, names=np.asarray(m.skeleton.names))
        write_bvh(tmp_path / "b.bvh", m.resample(30.0))
    png = tmp_path / "s.png"
    rc = run("render", tmp_path / "a.npz", tmp_path / "b.bvh", "--db", mirror_db, "--recording", "2_scott_0_1_1~mirror",
             "--start", 2, "--end", 4, "-o", png, "--frames", 4, "--size", "160x200", "--captions", "npz,bvh,db")
    assert rc == 0 and "rendered 3 panel(s), 30 frames" in capsys.readouterr().out
    img = iio.imread(png)
    assert img.shape[:2] == (3 * 200, 4 * 160)
    # the npz and the BVH are the same motion (the BVH at 30 fps, resampled back): same pixels
    assert np.abs(img[:200].astype(int) - img[200:400].astype(int)).mean() < 2.0
    mp4 = tmp_path / "v.mp4"
    assert run("render", "--db", mirror_db, "--start", 0, "--end", 2, "-o", mp4, "--size", "160x200") == 0
    assert mp4.stat().st_size > 1000


def test_render_errors(run, mirror_db, tmp_path):
    with pytest.raises(ParameterError, match=r"expected a \.mp4, \.gif or \.png"):
        run("render", "--db", mirror_db, "-o", tmp_path / "x.avi")
    with pytest.raises(ParameterError, match="at least one INPUT"):
        run("render", "-o", tmp_path / "x.png")
    with pytest.raises(ParameterError, match="--captions: expected 1"):
        run("render", "--db", mirror_db, "--end", 1, "-o", tmp_path / "x.png", "--captions", "a,b")
    with pytest.raises(ParameterError, match="stretch of --db"):
        run("render", tmp_path / "a.npz", "--start", 1, "-o", tmp_path / "x.png")
    bad = tmp_path / "bad.npz"
    np.savez(bad, something=np.zeros(3))
    with pytest.raises(InputFileError, match=r"bad\.npz: npz: expected joint positions"):
        run("render", bad, "-o", tmp_path / "x.png")
    np.savez(bad, positions=np.zeros((4, 3, 3)), parents=np.array([-1, 0, 1]))
    with pytest.raises(InputFileError, match="missing fps"):
        run("render", bad, "-o", tmp_path / "x.png")
