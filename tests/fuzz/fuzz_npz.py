"""Fuzz target: the SMPL-X npz reader (zip container, .npy headers, arrays)."""
from __future__ import annotations

import io
import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import _common  # noqa: E402
import atheris  # noqa: E402
import numpy as np  # noqa: E402

with atheris.instrument_imports():
    from gesturedb.errors import GestureDBError
    from gesturedb.io.smplx import read_smplx


def _seed(compressed: bool) -> bytes:
    buf = io.BytesIO()
    save = np.savez_compressed if compressed else np.savez
    save(buf, poses=np.zeros((3, 165), np.float32), trans=np.zeros((3, 3), np.float32), mocap_frame_rate=np.array(30.0))
    return buf.getvalue()


SEEDS = [_seed(False), _seed(True)]


def test_one_input(data: bytes) -> None:
    path = _common.tmp_file(data, ".npz")
    try:
        read_smplx(path)
    except GestureDBError:
        pass


if __name__ == "__main__":
    _common.run(test_one_input, SEEDS)
