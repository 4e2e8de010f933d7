"""Fuzz target: the mask language (tokenizer, parser) and its compilation against a few features."""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import _common  # noqa: E402
import atheris  # noqa: E402
import numpy as np  # noqa: E402

with atheris.instrument_imports():
    from gesturedb.control import compile_mask
    from gesturedb.errors import GestureDBError

_rng = np.random.default_rng(0)
N = 100
CONTROLS = {"left_wrist_height": _rng.normal(1.0, 0.2, N).astype(np.float32),
            "right_wrist_speed": np.abs(_rng.normal(0.3, 0.2, N)).astype(np.float32)}
NAMED = {"calm": compile_mask("right_wrist_speed < p50", controls=CONTROLS, named={}, n_frames=N).words}
SEEDS = [b"left_wrist_height > p85 and not calm", b"(right_wrist_speed < 20 cm/s) or left_wrist_height >= 1.1 m",
         b"not (calm or left_wrist_height < p15)"]


def test_one_input(data: bytes) -> None:
    text = data.decode("utf-8", errors="replace")
    try:
        compile_mask(text, controls=CONTROLS, named=NAMED, n_frames=N)
    except GestureDBError:
        pass


if __name__ == "__main__":
    _common.run(test_one_input, SEEDS)
