"""Fuzz target: the transcript readers (TextGrid, GENEA TSV, JSON); the first byte picks the format."""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import _common  # noqa: E402
import atheris  # noqa: E402

with atheris.instrument_imports():
    from gesturedb.errors import GestureDBError
    from gesturedb.io.transcripts import read_transcript

SUFFIXES = (".TextGrid", ".tsv", ".json")
SEEDS = [
    b"\x00" + b'File type = "ooTextFile"\nObject class = "TextGrid"\n\nxmin = 0\nxmax = 2\ntiers? <exists>\nsize = 1\n'
    b'item []:\n    item [1]:\n        class = "IntervalTier"\n        name = "words"\n        xmin = 0\n        xmax = 2\n'
    b'        intervals: size = 2\n        intervals [1]:\n            xmin = 0\n            xmax = 1\n'
    b'            text = "hello"\n        intervals [2]:\n            xmin = 1\n            xmax = 2\n'
    b'            text = "world"\n',
    b"\x01" + b"0.0\t0.5\thello\n0.5\t1.1\tworld\n",
    b"\x02" + b'{"words": [{"start": 0.0, "end": 0.5, "word": "hello"}, {"start": 0.6, "end": 1.0, "word": "you"}]}',
]


def test_one_input(data: bytes) -> None:
    if not data:
        return
    path = _common.tmp_file(data[1:], SUFFIXES[data[0] % len(SUFFIXES)])
    try:
        read_transcript(path)
    except GestureDBError:
        pass


if __name__ == "__main__":
    _common.run(test_one_input, SEEDS)
