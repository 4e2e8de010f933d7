"""Fuzz target: the BVH reader (hierarchy, MOTION header, frame lines)."""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import _common  # noqa: E402
import atheris  # noqa: E402

with atheris.instrument_imports():
    from gesturedb.errors import GestureDBError
    from gesturedb.io.bvh import read_bvh

SEEDS = [
    b"HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
    b" JOINT Spine\n {\n  OFFSET 0 10 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 5 0\n  }\n"
    b" }\n}\nMOTION\nFrames: 2\nFrame Time: 0.033333\n0 90 0 0 0 0 10 0 0\n0 91 0 1 2 3 11 1 1\n",
]


def test_one_input(data: bytes) -> None:
    path = _common.tmp_file(data, ".bvh")
    try:
        read_bvh(path)
    except GestureDBError:
        pass


if __name__ == "__main__":
    _common.run(test_one_input, SEEDS)
