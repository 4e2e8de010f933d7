"""Fuzz target: the glTF reader (GLB container, JSON, node tree, skin, buffers, accessors, animation).

Seeds are files the project's own writer makes (a small rig as .glb, and the same as .gltf JSON
with its buffer as a data: URI); the reader tells the two apart by their first bytes. Each input
is read as motion and as a rig (the rig path never reads the buffers).

Byte flips rarely keep JSON valid, so an input starting with b"EDIT" is instead a program of
edits applied to the writer's file: each picks a field of its JSON by walking it (or a byte of its
BIN chunk) and puts in an awkward value (-1, 0, 2**31, 10**12, NaN, a string, a list, nothing).
``python tests/fuzz/fuzz_gltf.py --file CRASH OUT.glb`` writes the file such an input stands for.
"""
from __future__ import annotations

import base64
import json
import os
import struct
import sys
import tempfile

sys.path.insert(0, os.path.dirname(__file__))
import _common  # noqa: E402
import atheris  # noqa: E402
import numpy as np  # noqa: E402

with atheris.instrument_imports():
    from gesturedb.errors import GestureDBError
    from gesturedb.io.gltf import read_gltf, read_gltf_rig
    from gesturedb.motion import Motion, Skeleton


def _seeds() -> list[bytes]:
    from gesturedb.io.gltf import write_glb

    sk = Skeleton(["Hips", "Spine", "Head"], [-1, 0, 1], [[0, 1, 0], [0, 0.3, 0], [0, 0.3, 0]], ["ZXY"] * 3)
    ang = np.linspace(0, 0.5, 3)
    q = np.zeros((3, 3, 4))
    q[..., 0], q[..., 2] = np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None]
    m = Motion(sk, 30.0, q, np.stack([ang, np.ones(3), np.zeros(3)], axis=1))
    seeds = []
    for mesh in (False, True):
        path = os.path.join(tempfile.mkdtemp(prefix="seed-", dir=_common._TMP), "seed.glb")
        write_glb(path, m, mesh=mesh)
        with open(path, "rb") as f:
            seeds.append(f.read())
    glb = seeds[0]
    (jlen,) = struct.unpack_from("<I", glb, 12)
    doc = json.loads(glb[20:20 + jlen])
    (blen,) = struct.unpack_from("<I", glb, 20 + jlen)
    blob = glb[28 + jlen:28 + jlen + blen]
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    seeds.append(json.dumps(doc).encode())
    return seeds


_AWKWARD = [-1, 0, 1, 2, 3, 4, 5, 7, 16, 252, 255, 5126, 5130, 2 ** 31, 2 ** 32 + 1, 10 ** 12, -(10 ** 12),
            float("nan"), float("inf"), 0.5, 1e-30, 1e30, "", "LINEAR", "STEP", "CUBICSPLINE", "rotation",
            "translation", "scale", "VEC3", "SCALAR", "MAT4", "../x.bin", "/dev/zero", "data:,", True, None,
            [], [0], [0, 0], [0, 0, 0, 1], {}]
_BASE = None


def _base():
    """The writer's .glb as (JSON dict, BIN bytes)."""
    global _BASE
    if _BASE is None:
        glb = _seeds()[0]
        (jlen,) = struct.unpack_from("<I", glb, 12)
        (blen,) = struct.unpack_from("<I", glb, 20 + jlen)
        _BASE = (glb[20:20 + jlen].decode(), glb[28 + jlen:28 + jlen + blen])
    return json.loads(_BASE[0]), bytearray(_BASE[1])


def _glb(doc, blob) -> bytes:
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    blob = bytes(blob) + b"\0" * (-len(blob) % 4)
    body = struct.pack("<I4s", len(j), b"JSON") + j + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def materialize(data: bytes) -> bytes:
    """The file an input stands for: itself, or for an b"EDIT" program the edited writer's file."""
    if not data.startswith(b"EDIT"):
        return data
    fdp = atheris.FuzzedDataProvider(data[4:])
    doc, blob = _base()
    for _ in range(fdp.ConsumeIntInRange(1, 6)):
        if fdp.ConsumeIntInRange(0, 7) == 0 and blob:  # a byte of the BIN chunk (key times, quaternions)
            blob[fdp.ConsumeIntInRange(0, len(blob) - 1)] = fdp.ConsumeIntInRange(0, 255)
            continue
        parent, key = None, None
        node = doc
        for _ in range(fdp.ConsumeIntInRange(1, 6)):  # walk down to a field
            if isinstance(node, dict) and node:
                k = sorted(node)[fdp.ConsumeIntInRange(0, len(node) - 1)]
            elif isinstance(node, list) and node:
                k = fdp.ConsumeIntInRange(0, len(node) - 1)
            else:
                break
            parent, key, node = node, k, node[k]
        if parent is None:
            continue
        choice = fdp.ConsumeIntInRange(0, len(_AWKWARD) + 1)
        if choice == len(_AWKWARD) and isinstance(parent, dict):
            del parent[key]
        elif choice == len(_AWKWARD) + 1:
            parent[key] = fdp.ConsumeIntInRange(-2 ** 40, 2 ** 40)
        else:
            parent[key] = json.loads(json.dumps(_AWKWARD[min(choice, len(_AWKWARD) - 1)]))
    return _glb(doc, blob)


def test_one_input(data: bytes) -> None:
    path = _common.tmp_file(materialize(data), ".gltf")
    for reader in (read_gltf, read_gltf_rig):
        try:
            reader(path)
        except GestureDBError:
            pass


if __name__ == "__main__":
    if sys.argv[1:2] == ["--file"]:
        with open(sys.argv[2], "rb") as f_in, open(sys.argv[3], "wb") as f_out:
            f_out.write(materialize(f_in.read()))
    else:
        _common.run(test_one_input, _seeds() + [b"EDIT" + bytes([k, 2 * k + 1, 3, k]) for k in range(8)])
