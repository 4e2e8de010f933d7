"""Atomic edits of an existing database: control features, saved masks."""
from __future__ import annotations

import hashlib
import os
import shutil

import h5py
import numpy as np
import pytest

import gesturedb
from gesturedb import control as masks
from gesturedb.cli.main import main
from gesturedb.db import edit as dbedit
from gesturedb.errors import ParameterError
from gesturedb.synth import Searcher


@pytest.fixture()
def db_copy(scott_db_path, tmp_path):
    p = tmp_path / "db.h5"
    shutil.copy(scott_db_path, p)
    return p


def digest(p):
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_control_features_can_be_added_to_an_existing_database(db_copy, scott_db_path):
    with h5py.File(db_copy, "r+") as h5:
        del h5["controls"]
        del h5["masks"]
    with gesturedb.open(db_copy) as db:
        assert db.controls == {}
    names = dbedit.add_control_features(db_copy)
    with gesturedb.open(db_copy) as db, gesturedb.open(scott_db_path) as ref:
        assert names == sorted(ref.controls)
        for k in ref.controls:
            np.testing.assert_array_equal(db.controls[k], ref.controls[k])
            assert db.control_units[k] == ref.control_units[k]
        for k in ref.masks:
            np.testing.assert_array_equal(db.masks[k], ref.masks[k])


def test_saved_mask_round_trip_and_use_in_synthesis(db_copy, scott_dir):
    res = dbedit.save_mask(db_copy, "calm_high", "left_wrist_height > p60 and left_wrist_speed < p70")
    with gesturedb.open(db_copy) as db:
        assert db.mask_definitions["calm_high"] == "left_wrist_height > p60 and left_wrist_speed < p70"
        want = (db.controls["left_wrist_height"] > np.percentile(db.controls["left_wrist_height"].astype(np.float64), 60)) & \
               (db.controls["left_wrist_speed"] < np.percentile(db.controls["left_wrist_speed"].astype(np.float64), 70))
        np.testing.assert_array_equal(masks.unpack_bits(db.masks["calm_high"], db.n_frames), want)
        assert res.n_set == int(want.sum())
        out = Searcher(db).synthesize(scott_dir / "inputs/2_scott_0_3_3.wav", control="calm_high")
        bits = masks.unpack_bits(db.masks["calm_high"], db.n_frames)
        for s in out.steps:  # first and last frame of every window satisfy the saved mask
            assert bits[s["db_frame"]] and bits[s["db_frame"] + s["out_end"] - s["out_start"] - 1]
    with pytest.raises(ParameterError, match="mask 'calm_high' already exists"):
        dbedit.save_mask(db_copy, "calm_high", "left_wrist_height > p10")
    dbedit.remove_mask(db_copy, "calm_high")
    with gesturedb.open(db_copy) as db:
        assert "calm_high" not in db.masks


def test_refused_edits_leave_the_file_untouched(db_copy):
    before = digest(db_copy)
    with pytest.raises(ParameterError, match="allows no frame"):
        dbedit.save_mask(db_copy, "never", "left_wrist_height > 100")
    with pytest.raises(ParameterError, match=r"unknown|Unknown|not a control"):
        dbedit.save_mask(db_copy, "typo", "left_wrist_hieght > p85")
    with pytest.raises(ParameterError, match="no such mask"):
        dbedit.remove_mask(db_copy, "nope")
    with pytest.raises(RuntimeError):
        with dbedit.edit(db_copy) as h5:
            del h5["masks"]
            raise RuntimeError("interrupted mid-edit")
    assert digest(db_copy) == before
    # no temporary file and no lock file remains (the lock file exists only while it is held)
    assert sorted(p.name for p in db_copy.parent.iterdir()) == ["db.h5"]


def test_masks_cli(db_copy, capsys):
    assert main(["masks", str(db_copy), "add", "up", "left_wrist_height > p85 or right_wrist_height > p85"]) == 0
    assert "saved up:" in capsys.readouterr().out
    assert main(["masks", str(db_copy), "list"]) == 0
    out = capsys.readouterr().out
    assert "left_wrist_height" in out and "up " in out and "p85" in out
    assert main(["masks", str(db_copy), "add", "bad", "left_wrist_height >> 3"]) == 2
    assert "gesturedb masks: error:" in capsys.readouterr().err


from diskfull import FAIL_AFTER as _FAIL_AFTER  # noqa: E402  (tests/diskfull.py)


@pytest.mark.parametrize("free", [300_000, -20_000], ids=["full-in-the-copy", "full-near-the-end"])
def test_disk_full_during_an_edit_is_one_line_and_keeps_the_database(db_copy, tmp_path, free):
    """Issue 41: an edit now writes its compact copy through HDF5 (not a byte copy), so a full
    disk must stay one line and exit 2 there too (no h5py tracebacks, no segfault), with the
    database byte for byte and no temporary file."""
    import subprocess
    import sys

    old = db_copy.read_bytes()
    budget = free if free > 0 else len(old) + free
    p = subprocess.run([sys.executable, "-c", _FAIL_AFTER, str(budget), "masks", str(db_copy), "add", "calm",
                        "hand_speed < p30"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, (p.returncode, p.stderr[-3000:])
    assert p.stderr.splitlines() == [f"gesturedb masks: error: {db_copy}: no space left on device while writing "
                                     "it; the previous file (if any) is unchanged"], p.stderr[-3000:]
    assert db_copy.read_bytes() == old
    assert sorted(os.listdir(tmp_path)) == ["db.h5"]


def test_disk_full_during_an_edit_on_a_real_small_file_system(db_copy, tmp_path):
    """The same on a tmpfs with room for the database but not its copy (root only; skips otherwise)."""
    import subprocess
    import sys

    folder = tmp_path / "small"
    folder.mkdir()
    old = db_copy.read_bytes()
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={len(old) // 1024 + 300}k", "tmpfs", str(folder)],
                       capture_output=True, text=True)
    if p.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({(p.stderr or p.stdout).strip()}); the injected variant runs")
    try:
        target = folder / "db.h5"
        target.write_bytes(old)
        p = subprocess.run([sys.executable, "-m", "gesturedb.cli", "keywords", str(target), "add", "like", "time"],
                           capture_output=True, text=True, timeout=300)
        assert p.returncode == 2, (p.returncode, p.stderr[-3000:])
        assert p.stderr.splitlines() == [f"gesturedb keywords: error: {target}: no space left on device while "
                                         "writing it; the previous file (if any) is unchanged"], p.stderr[-3000:]
        assert target.read_bytes() == old
        assert sorted(os.listdir(folder)) == ["db.h5"]
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)
