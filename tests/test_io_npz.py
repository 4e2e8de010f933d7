"""The joint-position npz (gesturedb.io.npz): what `gesturedb synth --npz` writes and `gesturedb render` reads."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.cli.render import load_positions
from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io import read_smplx
from gesturedb.io.npz import JOINT_POSITION_FIELDS, read_joint_positions, write_joint_positions


def test_write_then_read_gives_the_motion_back(scott_dir, tmp_path):
    m = read_smplx(scott_dir / "2_scott_0_1_1.npz")[:300]
    p = tmp_path / "pos.npz"
    write_joint_positions(p, m.positions, parents=m.skeleton.parents, fps=m.fps, names=m.skeleton.names)
    got = read_joint_positions(p)
    assert got.positions.dtype == np.float64 and got.positions.shape == m.positions.shape
    # stored as float32: a tenth of a millimetre at worst for a body
    assert np.abs(got.positions - m.positions).max() < 1e-6
    assert got.parents.dtype == np.int64 and got.parents.tolist() == list(m.skeleton.parents)
    assert got.fps == m.fps and got.names == list(m.skeleton.names)
    # the render command reads the same file the same way
    pos, par, fps, names = load_positions(p)
    assert np.array_equal(pos, got.positions) and np.array_equal(par, got.parents) and fps == got.fps
    assert names == got.names
    # names are optional
    write_joint_positions(p, m.positions[:2], parents=m.skeleton.parents, fps=15)
    got = read_joint_positions(p)
    assert got.names is None and got.fps == 15.0 and got.positions.shape[0] == 2


def test_writer_refuses_shapes_that_disagree_and_keeps_the_old_file(tmp_path):
    p = tmp_path / "pos.npz"
    write_joint_positions(p, np.zeros((4, 3, 3)), parents=[-1, 0, 1], fps=30)
    before = p.read_bytes()
    with pytest.raises(ParameterError, match=r"positions, parents: expected \(T, J, 3\) and \(J,\); got "
                                             r"\(4, 3, 3\) and \(2,\)"):
        write_joint_positions(p, np.zeros((4, 3, 3)), parents=[-1, 0], fps=30)
    with pytest.raises(ParameterError, match="fps: expected a positive frame rate; got 0"):
        write_joint_positions(p, np.zeros((4, 3, 3)), parents=[-1, 0, 1], fps=0)
    with pytest.raises(ParameterError, match=r"names: expected one per joint \(3\); got 2"):
        write_joint_positions(p, np.zeros((4, 3, 3)), parents=[-1, 0, 1], fps=30, names=["a", "b"])
    assert p.read_bytes() == before


def test_reader_names_what_is_missing_or_wrong(tmp_path):
    p = tmp_path / "bad.npz"
    np.savez(p, positions=np.zeros((4, 3, 3)))
    with pytest.raises(InputFileError, match=r"bad.npz: joint-position npz: expected fields positions, parents, fps; "
                                             r"missing parents, fps"):
        read_joint_positions(p)
    np.savez(p, positions=np.zeros((4, 3)), parents=np.array([-1, 0, 1]), fps=30.0)
    with pytest.raises(InputFileError, match=r"bad.npz: positions: expected \(T, J, 3\) with parents \(J,\); got "
                                             r"\(4, 3\) and \(3,\)"):
        read_joint_positions(p)
    np.savez(p, positions=np.zeros((4, 3, 3)), parents=np.array([-1, 0, 1]), fps=-1.0)
    with pytest.raises(InputFileError, match="bad.npz: fps: expected a positive frame rate; got -1.0"):
        read_joint_positions(p)
    np.savez(p, positions=np.zeros((4, 3, 3)), parents=np.array([-1, 0, 1]), fps=np.array([30.0, 60.0]))
    with pytest.raises(InputFileError, match="bad.npz: joint-position npz: not readable"):
        read_joint_positions(p)
    assert JOINT_POSITION_FIELDS == ("positions", "parents", "fps")
