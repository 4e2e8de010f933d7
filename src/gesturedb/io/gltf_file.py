"""The glTF container and its JSON, checked field by field (what `gesturedb.io.gltf` reads rigs and motion from).

`load` parses a .glb (GLB header and chunks) or a .gltf (JSON) itself and returns a `Doc`, whose
getters check each field before it is used, so a broken or hostile file gives one
`InputFileError` naming the file and the field (``accessors[3].count: ...``), never an
IndexError, a hang or unbounded memory:

- the file and every buffer file must be regular files (a FIFO or /dev/zero is refused, not read);
- a buffer is the GLB BIN chunk, a base64 data: URI, or a file inside the glTF file's own folder
  (after resolving links and ``..``) whose size is the buffer's byteLength; no more than
  byteLength bytes are read, and only when an accessor needs them;
- every accessor's bytes (count, stride, offset) must lie inside its bufferView, and every
  bufferView inside its buffer; values must be finite.
"""
from __future__ import annotations

import base64
import binascii
import json
import math
import os
import re
import stat
import struct
import urllib.parse

import numpy as np

from gesturedb.errors import InputFileError, ParameterError

__all__ = ["Doc", "load", "shown"]

_COMP = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_COMP_NAME = {5120: "BYTE", 5121: "UNSIGNED_BYTE", 5122: "SHORT", 5123: "UNSIGNED_SHORT", 5125: "UNSIGNED_INT",
              5126: "FLOAT"}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_GLB_MAGIC, _CHUNK_JSON, _CHUNK_BIN = b"glTF", 0x4E4F534A, 0x004E4942
_URI_SCHEME = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*:")
_MISSING = object()


def shown(v) -> str:
    """A JSON value as a short one-line repr for messages."""
    s = repr(v)
    return s if len(s) <= 60 else s[:57] + "..."


class Doc:
    """A glTF file's JSON with checked access: each getter names the field in its error."""

    def __init__(self, path, root: dict, bin_chunk):
        self.path, self.root, self.bin_chunk = path, root, bin_chunk
        self._buffers, self._accessors = {}, {}

    def fail(self, where: str, problem: str):
        raise InputFileError(self.path, f"{where}: {problem}")

    def items(self, key: str) -> list:
        """A top-level array (``nodes``, ``accessors``...); absent is empty."""
        v = self.root.get(key, [])
        if not isinstance(v, list):
            self.fail(key, f"expected an array; got {shown(v)}")
        return v

    def item(self, key: str, i: int) -> dict:
        v = self.items(key)[i]
        if not isinstance(v, dict):
            self.fail(f"{key}[{i}]", f"expected an object; got {shown(v)}")
        return v

    def integer(self, obj: dict, key: str, where: str, *, lo: int = 0, hi: int | None = None, default=_MISSING):
        v = obj.get(key, _MISSING)
        if v is _MISSING or v is None:
            if default is _MISSING:
                self.fail(f"{where}.{key}", "missing (required)")
            return default
        if isinstance(v, bool) or not isinstance(v, int) or v < lo or (hi is not None and v > hi):
            rng = f"from {lo} to {hi}" if hi is not None else f">= {lo}"
            self.fail(f"{where}.{key}", f"expected an integer {rng}; got {shown(v)}")
        return v

    def index(self, obj: dict, key: str, where: str, into: str, *, default=_MISSING):
        """An index into the top-level array ``into``."""
        n = len(self.items(into))
        v = obj.get(key, _MISSING)
        if (v is _MISSING or v is None) and default is not _MISSING:
            return default
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < n:
            want = f"an index into {into} (0 to {n - 1})" if n else f"nothing: the file has no {into}"
            self.fail(f"{where}.{key}", f"expected {want}; got {'nothing' if v is _MISSING else shown(v)}")
        return v

    def text(self, obj: dict, key: str, where: str, *, choices=None, default=_MISSING):
        v = obj.get(key, _MISSING)
        if v is _MISSING or v is None:
            if default is _MISSING:
                self.fail(f"{where}.{key}", "missing (required)")
            return default
        if not isinstance(v, str) or (choices is not None and v not in choices):
            want = f"one of {', '.join(choices)}" if choices is not None else "a string"
            self.fail(f"{where}.{key}", f"expected {want}; got {shown(v)}")
        return v

    def numbers(self, obj: dict, key: str, where: str, n: int, default):
        v = obj.get(key)
        if v is None:
            return np.asarray(default, float)
        if (not isinstance(v, list) or len(v) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            self.fail(f"{where}.{key}", f"expected {n} finite numbers; got {shown(v)}")
        return np.asarray(v, float)

    # --- buffers and accessors

    def buffer(self, i: int) -> bytes:
        """``buffers[i]``'s bytes (exactly byteLength of them), loaded once."""
        if i not in self._buffers:
            self._buffers[i] = self._load_buffer(i)
        return self._buffers[i]

    def _load_buffer(self, i: int) -> bytes:
        where = f"buffers[{i}]"
        b = self.item("buffers", i)
        n = self.integer(b, "byteLength", where, lo=1)
        uri = self.text(b, "uri", where, default=None)
        if uri is None:
            if i != 0 or self.bin_chunk is None:
                self.fail(f"{where}.uri", "missing: only buffers[0] of a .glb with a BIN chunk may go without one")
            if len(self.bin_chunk) < n:
                self.fail(f"{where}.byteLength", f"expected at most the {len(self.bin_chunk)} bytes of the GLB "
                                                 f"BIN chunk; got {n}")
            return bytes(self.bin_chunk[:n])
        if uri.startswith("data:"):
            head, sep, payload = uri.partition(",")
            if not sep or not head.endswith(";base64"):
                self.fail(f"{where}.uri", f"expected a base64 data: URI (data:application/octet-stream;base64,...); "
                                          f"got {shown(uri)}")
            try:
                data = base64.b64decode(payload, validate=True)
            except (binascii.Error, ValueError) as exc:
                self.fail(f"{where}.uri", f"bad base64 in the data: URI ({exc})")
            if len(data) != n:
                self.fail(f"{where}.byteLength", f"expected the {len(data)} bytes the data: URI holds; got {n}")
            return data
        return self._external(where, uri, n)

    def _external(self, where: str, uri: str, n: int) -> bytes:
        """A buffer file beside the glTF: relative, inside its folder, regular, byteLength bytes long."""
        if _URI_SCHEME.match(uri):
            self.fail(f"{where}.uri", f"expected a data: URI or a path relative to the glTF file; got {shown(uri)}")
        rel = urllib.parse.unquote(uri)
        if "\0" in rel or os.path.isabs(rel) or rel.startswith(("/", "\\")):
            self.fail(f"{where}.uri", f"expected a path relative to the glTF file's folder; got {shown(uri)}")
        base = os.path.realpath(os.path.dirname(os.path.abspath(os.fspath(self.path))))
        target = os.path.realpath(os.path.join(base, rel))
        if os.path.commonpath([base, target]) != base:
            self.fail(f"{where}.uri", f"{shown(uri)} leads outside the glTF file's folder {base}")
        with _open_regular(target, lambda problem: self.fail(f"{where}.uri", f"{shown(uri)}: {problem}")) as (f, size):
            if size != n:
                self.fail(f"{where}.byteLength", f"expected the {size} bytes of {shown(uri)}; got {n}")
            data = f.read(n)
        if len(data) != n:
            self.fail(f"{where}.uri", f"{shown(uri)} ended after {len(data)} of {n} bytes while being read")
        return data

    def accessor(self, i: int, used_as: str, *, types, comps, normalized_ints: bool = False) -> np.ndarray:
        """``accessors[i]`` as float64 (count, n), checked against its bufferView and buffer.

        ``used_as`` names the field that points at it (``animations[0].samplers[2].output``);
        ``types``/``comps`` are what that use allows; ``normalized_ints``: integer components are
        allowed when normalized (mapped to [0, 1] or [-1, 1] as glTF says).
        """
        where = f"accessors[{i}]"
        acc = self.item("accessors", i)
        comp = self.integer(acc, "componentType", where)
        typ = self.text(acc, "type", where, choices=tuple(_NCOMP))
        if comp not in _COMP:
            self.fail(f"{where}.componentType", f"expected one of {', '.join(map(str, _COMP))}; got {comp}")
        normalized = acc.get("normalized", False)
        if not isinstance(normalized, bool):
            self.fail(f"{where}.normalized", f"expected true or false; got {shown(normalized)}")
        ok_comp = comp in comps or (normalized_ints and normalized and comp != 5126 and comp != 5125)
        if typ not in types or not ok_comp:
            want = " or ".join(types) + " of " + " or ".join(_COMP_NAME[c] for c in comps)
            if normalized_ints:
                want += " (or normalized integers)"
            self.fail(f"{used_as}", f"expected an accessor of {want}; accessors[{i}] is {typ} of "
                                    f"{_COMP_NAME[comp]}{' normalized' if normalized else ''}")
        if i in self._accessors:  # channels share key times: read each accessor once
            return self._accessors[i]
        count = self.integer(acc, "count", where, lo=1)
        if acc.get("sparse") is not None:
            self.fail(f"{where}.sparse", "sparse accessors are not supported")
        if acc.get("bufferView") is None:
            self.fail(f"{where}.bufferView", "missing (accessors without data, all zeros, are not supported)")
        bvi = self.index(acc, "bufferView", where, "bufferViews")
        off = self.integer(acc, "byteOffset", where, default=0)
        bwhere = f"bufferViews[{bvi}]"
        bv = self.item("bufferViews", bvi)
        bi = self.index(bv, "buffer", bwhere, "buffers")
        bv_off = self.integer(bv, "byteOffset", bwhere, default=0)
        bv_len = self.integer(bv, "byteLength", bwhere, lo=1)
        stride = self.integer(bv, "byteStride", bwhere, lo=4, hi=252, default=None)
        dt = np.dtype(_COMP[comp])
        n = _NCOMP[typ]
        elem = n * dt.itemsize
        if stride is not None and stride < elem:
            self.fail(f"{bwhere}.byteStride", f"expected at least the {elem} bytes of one element of "
                                              f"accessors[{i}] ({typ} of {_COMP_NAME[comp]}); got {stride}")
        stride = stride or elem
        need = off + stride * (count - 1) + elem
        if need > bv_len:
            self.fail(f"{where}.count", f"{count} elements of {elem} bytes (stride {stride}) from byteOffset {off} "
                                        f"need {need} bytes; {bwhere}.byteLength is {bv_len}")
        buf = self.buffer(bi)
        if bv_off + bv_len > len(buf):
            self.fail(f"{bwhere}.byteOffset", f"bytes {bv_off} to {bv_off + bv_len} lie past the end of "
                                              f"buffers[{bi}] ({len(buf)} bytes)")
        out = np.ndarray((count, n), dt, buffer=buf, offset=bv_off + off, strides=(stride, dt.itemsize))
        out = out.astype(np.float64)
        if normalized and dt.kind in "iu":
            out = np.maximum(out / np.iinfo(dt).max, -1.0)
        if not np.all(np.isfinite(out)):
            bad = int(np.argwhere(~np.isfinite(out))[0, 0])
            self.fail(used_as, f"accessors[{i}] element {bad} is not finite: {out[bad].tolist()}")
        self._accessors[i] = out
        return out


class _open_regular:
    """Open ``path`` for reading without blocking (a FIFO must not hang) and only if it is a regular file.

    ``fail(problem)`` raises the caller's error. Gives ``(file, size)``.
    """

    def __init__(self, path, fail):
        self.path, self.fail = path, fail

    def __enter__(self):
        flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
        try:
            fd = os.open(self.path, flags)
        except FileNotFoundError:
            self.fail("no such file")
        except OSError as exc:
            self.fail(f"cannot open it ({exc.strerror})")
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            os.close(fd)
            kind = "a folder" if stat.S_ISDIR(st.st_mode) else "a device, pipe or socket"
            self.fail(f"expected a regular file; got {kind}")
        self.f = os.fdopen(fd, "rb")
        return self.f, st.st_size

    def __exit__(self, *exc):
        self.f.close()


def load(path) -> Doc:
    """Parse a .glb (by its magic bytes) or a .gltf (JSON) into a checked document."""
    if isinstance(path, bool) or not isinstance(path, (str, bytes, os.PathLike)):
        raise ParameterError(f"path: expected a file path; got {type(path).__name__}")

    def fail(problem):
        raise InputFileError(path, problem)

    with _open_regular(path, fail) as (f, size):
        data = f.read(size)
    bin_chunk = None
    if data[:4] == _GLB_MAGIC:
        if len(data) < 12:
            fail(f"GLB header: expected 12 bytes; the file has {len(data)}")
        version, length = struct.unpack_from("<II", data, 4)
        if version != 2:
            fail(f"GLB header version: expected 2; got {version}")
        if length != len(data):
            fail(f"GLB header length: says {length} bytes; the file has {len(data)}"
                 + (" (truncated)" if length > len(data) else ""))
        pos, k, raw = 12, 0, None
        while pos < length:
            if pos + 8 > length:
                fail(f"GLB chunk {k}: its 8-byte header at byte {pos} runs past the end of the file ({length} bytes)")
            clen, ctype = struct.unpack_from("<II", data, pos)
            pos += 8
            if pos + clen > length:
                fail(f"GLB chunk {k} length: {clen} bytes from byte {pos} run past the end of the file "
                     f"({length} bytes; truncated)")
            if k == 0 and ctype != _CHUNK_JSON:
                fail(f"GLB chunk 0 type: expected JSON (0x{_CHUNK_JSON:08X}); got 0x{ctype:08X}")
            if k == 0:
                raw = data[pos:pos + clen]
            elif ctype == _CHUNK_BIN:
                if k != 1:
                    fail(f"GLB chunk {k}: a BIN chunk must be the second chunk")
                bin_chunk = memoryview(data)[pos:pos + clen]
            elif ctype == _CHUNK_JSON:
                fail(f"GLB chunk {k}: a second JSON chunk")
            pos += clen
            k += 1
        if raw is None:
            fail("GLB: no JSON chunk")
    elif os.fspath(path)[-4:].lower() in (".glb", b".glb"):
        fail(f"GLB header: expected the magic bytes b'glTF'; got {bytes(data[:4])!r}")
    else:
        raw = data
    try:
        root = json.loads(bytes(raw).decode("utf-8-sig"))
    except UnicodeDecodeError as exc:
        fail(f"JSON: not UTF-8 text ({exc.reason} at byte {exc.start})")
    except json.JSONDecodeError as exc:
        fail(f"JSON: {exc.msg} at line {exc.lineno} column {exc.colno}")
    except ValueError as exc:  # e.g. an integer longer than Python converts
        fail(f"JSON: {str(exc).splitlines()[0]}")
    except RecursionError:
        fail("JSON: nested too deeply")
    if not isinstance(root, dict):
        fail(f"JSON: expected an object at the top; got {type(root).__name__}")
    doc = Doc(path, root, bin_chunk)
    asset = root.get("asset")
    if not isinstance(asset, dict):
        doc.fail("asset", f"expected an object with version '2.0' (glTF 2.0); got {shown(asset)}")
    version = asset.get("version")
    if not (isinstance(version, str) and re.fullmatch(r"2\.\d+", version)):
        doc.fail("asset.version", f"expected '2.0' (glTF 2.0); got {shown(version)}")
    return doc
