"""Fuzz target: the refiner's checkpoint reader (torch zip archive, weights-only pickle, every entry).

Seeds are checkpoints the project's own trainer writes (a tiny generator and critic). Each input
is loaded as ``refiner apply`` loads it (:meth:`Refiner.load`, which builds the generator) and as
``refiner train --resume`` reads it (``read_checkpoint(training=True)``).

Byte flips mostly break the archive's checksums, so an input starting with b"EDIT" is instead a
program of edits applied to the trainer's checkpoint before it is saved: each picks an entry (or
a field of ``config``, ``features``, a weight) and puts in an awkward value (-1, 0, 2**31, NaN, a
string, a list, a tensor of another shape or type, nothing).
``python tests/fuzz/fuzz_checkpoint.py --file CRASH OUT.pt`` writes the file such an input stands for.
"""
from __future__ import annotations

import io
import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
import _common  # noqa: E402
import atheris  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402  (imported before instrumenting: only gesturedb's code is instrumented)

with atheris.instrument_imports():
    from gesturedb.errors import GestureDBError
    from gesturedb.refiner.data import TrainingData
    from gesturedb.refiner.train import Refiner, TrainConfig, Trainer, read_checkpoint

torch.set_num_threads(1)
FEATURES = {"joint_names": ["root", "spine", "head"], "parents": [-1, 0, 1], "fps": 15.0, "audio_channels": 28,
            "n_mfcc": 13}
_BASE = None


def _state() -> dict:
    """A real checkpoint's entries: two iterations of a width-4 refiner on random windows."""
    global _BASE
    if _BASE is None:
        rng = np.random.default_rng(0)
        data = TrainingData(frame_audio=rng.standard_normal((40, 28)).astype(np.float32),
                            frame_real=rng.standard_normal((40, 12)).astype(np.float32),
                            knn=rng.standard_normal((4, 12, 16)).astype(np.float32), joints=np.arange(1, 3),
                            starts=3 * np.arange(4), ks=np.ones(4, np.int64))
        tr = Trainer(data, TrainConfig(width=4, batch=2, n_critic=1), "id", FEATURES)
        tr.step()
        buf = io.BytesIO()
        torch.save(tr.state(), buf)
        _BASE = buf.getvalue()
    return torch.load(io.BytesIO(_BASE), weights_only=True)


def _save(ck) -> bytes:
    buf = io.BytesIO()
    torch.save(ck, buf)
    return buf.getvalue()


def _seeds() -> list[bytes]:
    return [_save(_state())]


_AWKWARD = [-1, 0, 1, 2, 3, 28, 1024, 1025, 30000, 2 ** 31, 2 ** 63, -(2 ** 63), float("nan"), float("inf"), 0.5,
            1e-30, 1e30, "", "x", "width", True, None, [], [0], [0, 0], [1, 999], [-1, 0, 1], {}, {"x": 1},
            (0.5, 0.9)]


def _awkward_tensor(fdp):
    dtype = [torch.float32, torch.float64, torch.int64, torch.uint8, torch.bool][fdp.ConsumeIntInRange(0, 4)]
    shape = [fdp.ConsumeIntInRange(0, 5) for _ in range(fdp.ConsumeIntInRange(0, 3))]
    t = torch.zeros(shape, dtype=dtype)
    if t.numel() and t.is_floating_point():
        t.view(-1)[fdp.ConsumeIntInRange(0, t.numel() - 1)] = [float("nan"), float("inf"), 1e30][
            fdp.ConsumeIntInRange(0, 2)]
    return t


def materialize(data: bytes) -> bytes:
    """The file an input stands for: itself, or for an b"EDIT" program the edited trainer's checkpoint."""
    if not data.startswith(b"EDIT"):
        return data
    fdp = atheris.FuzzedDataProvider(data[4:])
    ck = _state()
    for _ in range(fdp.ConsumeIntInRange(1, 4)):
        parent = ck
        keys = sorted(ck)
        key = keys[fdp.ConsumeIntInRange(0, len(keys) - 1)]
        if isinstance(ck[key], dict) and ck[key] and fdp.ConsumeBool():  # a field of config, features, a weight
            parent = ck[key]
            inner = sorted(parent, key=str)
            key = inner[fdp.ConsumeIntInRange(0, len(inner) - 1)]
        choice = fdp.ConsumeIntInRange(0, len(_AWKWARD) + 2)
        if choice == len(_AWKWARD):
            del parent[key]
        elif choice == len(_AWKWARD) + 1:
            parent[key] = _awkward_tensor(fdp)
        elif choice == len(_AWKWARD) + 2:
            parent[key] = fdp.ConsumeIntInRange(-2 ** 40, 2 ** 40)
        else:
            parent[key] = _AWKWARD[choice]
    return _save(ck)


def test_one_input(data: bytes) -> None:
    path = _common.tmp_file(materialize(data), ".pt")
    for load in (Refiner.load, lambda p: read_checkpoint(p, training=True)):
        try:
            load(path)
        except GestureDBError:
            pass


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--file":
        with open(sys.argv[2], "rb") as f, open(sys.argv[3], "wb") as out:
            out.write(materialize(f.read()))
        sys.exit(0)
    _common.run(test_one_input, _seeds() + [b"EDIT" + bytes(range(i, i + 40)) for i in range(0, 200, 20)])
