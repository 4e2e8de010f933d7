"""The command line: exit codes, one-line errors, and files written, on the real data."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from gesturedb.cli.main import main


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_build_info_export_synth(scott_dir, tmp_path, capsys):
    db = tmp_path / "scott.h5"
    code, out, err = run(capsys, "build", scott_dir, "-o", db, "-j", "1")
    assert code == 0, err
    assert "paired 1 recording(s)" in err and "2_scott_0_1_1.npz + 2_scott_0_1_1.wav + 2_scott_0_1_1.TextGrid" in err
    assert "953 frames" in out

    code, out, err = run(capsys, "info", db)
    assert code == 0 and "953 frames at 15 fps" in out and "scott" in out and "chunks       15 x 64" in out
    assert "pose 150 values/frame (frames 2 apart; the motion's timescale 0.16" in out
    code, out, _ = run(capsys, "info", db, "--json")
    info = json.loads(out)
    timescale = info["features"].pop("motion_timescale_s")
    assert info["frames"] == 953 and info["features"] == {"pose": 150, "audio": 14, "pose_stride": 2}
    assert 0.15 < timescale < 0.18

    bvh = tmp_path / "stretch.bvh"
    code, out, err = run(capsys, "export", db, "--recording", "2_scott_0_1_1", "--start", 10, "--end", 12, "-o", bvh)
    assert code == 0, err
    import gesturedb
    from gesturedb.io import read_bvh

    m = read_bvh(bvh)
    assert m.rotations.shape[0] == 30 and m.fps == pytest.approx(15.0)
    with gesturedb.open(db) as d:
        # the exported stretch reproduces the database's joint positions (up to the root placement)
        ref = d.joint_positions[150:180].astype(np.float64)
        order = [m.skeleton.names.index(n) for n in d.joint_names]  # BVH is written depth-first
    pos = m.positions[:, order]
    np.testing.assert_allclose(pos - pos[:, :1], ref - ref[:, :1], atol=1e-4)

    out_bvh = tmp_path / "synth.bvh"
    code, out, err = run(capsys, "synth", db, "--audio", scott_dir / "inputs/2_scott_0_3_3.wav",
                         "--transcript", scott_dir / "inputs/2_scott_0_3_3.TextGrid",
                         "-o", out_bvh, "--npz", tmp_path / "synth.npz", "--export-fps", 30)
    assert code == 0, err
    prov = json.loads((tmp_path / "synth.provenance.json").read_text())
    npz = np.load(tmp_path / "synth.npz")
    assert npz["positions"].shape[0] == read_bvh(out_bvh).rotations.shape[0]
    assert abs(npz["positions"].shape[0] / 30 - prov["duration_s"]) < 0.1


def test_bad_inputs_exit_2_with_one_line(scott_dir, data_dir, tmp_path, capsys):
    # a skeleton without finger joints: the error lists what it found
    d = tmp_path / "walk"
    d.mkdir()
    shutil.copy(data_dir / "bvh-foreign/AV_8Walk_Meredith_HVHA_Rep1.bvh", d / "walk.bvh")
    import soundfile as sf

    sf.write(d / "walk.wav", np.zeros(int(16000 * 8.9), np.float32), 16000)
    code, out, err = run(capsys, "build", d, "-o", tmp_path / "w.h5", "-q")
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gesturedb build: error: ") and "walk.bvh" in lines[0]
    assert "left_index1" in lines[0] and "LeftHand" in lines[0]
    assert not list(tmp_path.glob("*.h5")) and not list(tmp_path.glob(".*tmp"))

    # ... and builds with an explicit joint mapping
    mapping = json.dumps({"left_index1": "LeftHandThumb1", "right_index1": "RightHandThumb1",
                          "left_pinky1": "LeftHand_End", "right_pinky1": "RightHand_End"})
    code, out, err = run(capsys, "build", d, "-o", tmp_path / "w.h5", "-q", "--joint-map", mapping)
    assert code == 0, err
    # a database from a centimetre BVH exports back in the source's units
    code, out, err = run(capsys, "export", tmp_path / "w.h5", "--recording", "walk", "--start", 1, "--end", 2,
                         "-o", tmp_path / "walk_out.bvh")
    assert code == 0, err
    from gesturedb.io import read_bvh

    src, back = read_bvh(d / "walk.bvh"), read_bvh(tmp_path / "walk_out.bvh")
    assert back.skeleton.length_unit_m == src.skeleton.length_unit_m == 0.0254  # guessed: inches
    np.testing.assert_allclose(back.skeleton.offsets, src.skeleton.offsets, atol=1e-6)
    np.testing.assert_allclose(back.positions[0], src.resample(15.0).positions[15], atol=1e-4)

    code, out, err = run(capsys, "info", tmp_path / "missing.h5")
    assert code == 2 and "missing.h5: no such file" in err
    code, out, err = run(capsys, "export", tmp_path / "w.h5", "--recording", "nope", "-o", tmp_path / "x.bvh")
    assert code == 2 and "no recording named 'nope'" in err and "walk" in err
