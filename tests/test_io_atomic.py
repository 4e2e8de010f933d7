"""Outputs appear whole or not at all: gesturedb.io.atomic and the writers that use it."""
from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from gesturedb.errors import InputFileError
from gesturedb.io.atomic import atomic_open, write_text
from gesturedb.io.bvh import read_bvh, write_bvh


class Boom(Exception):
    pass


def test_success_replaces_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "out.txt"
    p.write_text("old")
    write_text(p, "new é")
    assert p.read_text(encoding="utf-8") == "new é"
    assert sorted(os.listdir(tmp_path)) == ["out.txt"]


def test_failure_inside_the_block_keeps_the_previous_file(tmp_path):
    p = tmp_path / "out.bin"
    p.write_bytes(b"previous output")
    with pytest.raises(Boom):
        with atomic_open(p, "wb") as f:
            f.write(b"half of the new")
            raise Boom()
    assert p.read_bytes() == b"previous output"
    assert sorted(os.listdir(tmp_path)) == ["out.bin"]


def test_keyboard_interrupt_is_not_swallowed_and_cleans_up(tmp_path):
    p = tmp_path / "x.txt"
    with pytest.raises(KeyboardInterrupt):
        with atomic_open(p) as f:
            f.write("x")
            raise KeyboardInterrupt
    assert os.listdir(tmp_path) == []


def test_unwritable_place_names_the_file(tmp_path):
    target = tmp_path / "missing-folder" / "x.txt"
    with pytest.raises(InputFileError) as err:
        write_text(target, "x")
    assert str(err.value).startswith(f"{target}: cannot write")
    assert os.listdir(tmp_path) == []


def test_permissions_follow_the_umask_like_open(tmp_path):
    old = os.umask(0o022)
    try:
        write_text(tmp_path / "a.txt", "x")
        with open(tmp_path / "b.txt", "w") as f:
            f.write("x")
    finally:
        os.umask(old)
    mode = lambda n: stat.S_IMODE(os.stat(tmp_path / n).st_mode)  # noqa: E731
    assert mode("a.txt") == mode("b.txt") == 0o644


def test_only_write_modes(tmp_path):
    with pytest.raises(ValueError, match="expected mode 'w' or 'wb', got 'a'"):
        with atomic_open(tmp_path / "x", "a"):
            pass


def test_a_failing_bvh_write_keeps_the_previous_bvh(tmp_path, data_dir, monkeypatch):
    m = read_bvh(data_dir / "bvh-foreign" / "AV_8Walk_Meredith_HVHA_Rep1.bvh")[:5]
    p = tmp_path / "out.bvh"
    write_bvh(p, m)
    before = p.read_bytes()

    def disk_full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savetxt", disk_full)
    with pytest.raises(InputFileError, match="out.bvh: cannot write: No space left on device"):
        write_bvh(p, m[:3])
    assert p.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["out.bvh"]
