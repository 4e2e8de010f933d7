"""The wire format of ``gesturedb serve``, shared by the server and :mod:`gesturedb.serve.client`.

Everything here is pure numpy and JSON, so an engine-side client needs nothing
of the server. The prose version with examples is ``docs/live.md``.

Frames message (binary, little-endian), sent by the server::

    offset  size            field
    0       4               magic b"GDBF"
    4       4   uint32      layout version (:data:`LAYOUT_VERSION`)
    8       4   uint32      start: output frame index of the first frame here
    12      4   uint32      count: frames in this message (may be 0)
    16      4   uint32      J: joints of the skeleton (``GET /skeleton``)
    20      4   uint32      P: bytes of the provenance JSON at the end
    24      4   uint32      samples: audio samples of the stream the server had received when
                            these frames became final (0 outside a stream)
    28      count*(3+4J)*4  float32 frames, row-major: per frame the root position
                            (x, y, z metres, y up) then J local unit quaternions
                            (w, x, y, z) in skeleton order
    ...     P               UTF-8 JSON list: the steps whose frames are final now,
                            the same keys as SynthResult.steps

Audio sent by a client is a binary message of mono samples at the rate its
``start`` message declared: ``pcm16`` (int16 little-endian) or ``f32``
(float32 little-endian in [-1, 1]).
"""
from __future__ import annotations

import json
import math
import struct
from typing import NamedTuple

import numpy as np

from gesturedb.errors import ParameterError

#: Version of this protocol; ``start`` may name it and ``ready`` reports it.
PROTOCOL_VERSION = 1
#: Version of the binary frames layout (the second header field).
LAYOUT_VERSION = 1
FRAMES_MAGIC = b"GDBF"
_HEADER = struct.Struct("<4sIIIIII")
#: Bytes before the float32 frames; a multiple of 4, so the frames can be viewed in place (Float32Array).
HEADER_BYTES = _HEADER.size
#: Audio sample formats a client may declare: name -> numpy dtype of one sample.
AUDIO_FORMATS = {"pcm16": np.dtype("<i2"), "f32": np.dtype("<f4")}
#: Sample rates a client may declare, Hz.
MIN_SAMPLE_RATE, MAX_SAMPLE_RATE = 8000, 192000

#: WebSocket close codes used by the server (RFC 6455 section 7.4.1).
CLOSE_NORMAL = 1000
CLOSE_GOING_AWAY = 1001
CLOSE_POLICY = 1008      # a malformed or out-of-order message, too many errors, idle too long
CLOSE_TOO_BIG = 1009     # a message over the server's limit
CLOSE_INTERNAL = 1011    # the synthesizer failed (a bug); other clients are unaffected
CLOSE_TRY_LATER = 1013   # the server holds its maximum of streams


def frame_width(n_joints: int) -> int:
    """float32 values per frame: root position (3) and one quaternion per joint (4 J)."""
    return 3 + 4 * int(n_joints)


class FramesMessage(NamedTuple):
    """A decoded frames message (:func:`unpack_frames`)."""

    start: int
    root_positions: np.ndarray
    rotations: np.ndarray
    steps: list
    samples: int


def pack_frames(start: int, root_positions: np.ndarray, rotations: np.ndarray, steps=(), *, samples: int = 0) -> bytes:
    """Encode frames and their steps' provenance as one binary frames message.

    Parameters
    ----------
    start : int
        Output frame index of the first frame.
    root_positions : ndarray [shape=(F, 3)], metres
    rotations : ndarray [shape=(F, J, 4)]
        Local unit quaternions (w, x, y, z).
    steps : list of dict
        Provenance of the steps completed with these frames; values that JSON
        cannot hold as finite numbers become null.
    samples : int
        Audio samples of the stream received when the frames became final (what a
        client times its latency from; 0 outside a stream).
    """
    root = np.asarray(root_positions, dtype="<f4")
    rot = np.asarray(rotations, dtype="<f4")
    if root.ndim != 2 or root.shape[1] != 3 or rot.ndim != 3 or rot.shape[2] != 4 or rot.shape[0] != root.shape[0]:
        raise ParameterError(f"frames: expected root (F, 3) and rotations (F, J, 4); got {root.shape} and {rot.shape}")
    count, n_joints = rot.shape[0], rot.shape[1]
    data = np.concatenate([root, rot.reshape(count, 4 * n_joints)], axis=1)
    tail = json.dumps(json_safe(list(steps)), allow_nan=False, separators=(",", ":")).encode()
    return (_HEADER.pack(FRAMES_MAGIC, LAYOUT_VERSION, int(start), count, n_joints, len(tail), int(samples))
            + data.tobytes() + tail)


def unpack_frames(message: bytes) -> FramesMessage:
    """Decode a binary frames message.

    Returns
    -------
    FramesMessage
        ``start`` (int), ``root_positions`` (ndarray [shape=(F, 3)], float32, metres),
        ``rotations`` (ndarray [shape=(F, J, 4)], float32, w x y z), ``steps`` (list of
        dict), ``samples`` (int).

    Raises
    ------
    ParameterError
        A message that is not a frames message of this layout, or whose sizes disagree.
    """
    message = bytes(message)
    if len(message) < HEADER_BYTES:
        raise ParameterError(f"frames message: expected at least {HEADER_BYTES} bytes; got {len(message)}")
    magic, layout, start, count, n_joints, n_tail, samples = _HEADER.unpack_from(message)
    if magic != FRAMES_MAGIC or layout != LAYOUT_VERSION:
        raise ParameterError(f"frames message: expected magic {FRAMES_MAGIC!r} layout {LAYOUT_VERSION}; "
                             f"got {magic!r} layout {layout}")
    n_data = count * frame_width(n_joints) * 4
    if len(message) != HEADER_BYTES + n_data + n_tail:
        raise ParameterError(f"frames message: header says {HEADER_BYTES + n_data + n_tail} bytes "
                             f"({count} frames of {n_joints} joints, {n_tail} bytes of steps); got {len(message)}")
    data = np.frombuffer(message, dtype="<f4", count=count * frame_width(n_joints), offset=HEADER_BYTES)
    data = data.reshape(count, frame_width(n_joints))
    steps = json.loads(message[HEADER_BYTES + n_data:].decode()) if n_tail else []
    return FramesMessage(start, data[:, :3].copy(), data[:, 3:].reshape(count, n_joints, 4).copy(), steps, samples)


def json_safe(value):
    """``value`` with non-finite floats replaced by None and numpy scalars by Python ones (strict JSON)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def audio_samples(message: bytes, fmt: str) -> int:
    """How many samples an audio message holds, once :func:`decode_audio` would accept it.

    What a server checks per message when it keeps the bytes and decodes them later, joined:
    the samples of joined messages are those of each message in turn, for either format.

    Raises
    ------
    ParameterError
        A length that is not a whole number of samples, or non-finite float samples.
    """
    itemsize = AUDIO_FORMATS[fmt].itemsize
    if len(message) % itemsize:
        raise ParameterError(f"audio: expected a whole number of {fmt} samples ({itemsize} bytes each); "
                             f"got {len(message)} bytes")
    if fmt != "pcm16":
        _check_finite(np.frombuffer(message, dtype=AUDIO_FORMATS[fmt]))
    return len(message) // itemsize


def _check_finite(x: np.ndarray) -> None:
    if not np.all(np.isfinite(x)):
        raise ParameterError(f"audio: expected finite f32 samples; got {int(np.count_nonzero(~np.isfinite(x)))} "
                             "NaN or infinite values")


def decode_audio(message: bytes, fmt: str) -> np.ndarray:
    """Samples of an audio message as float32 in [-1, 1].

    Raises
    ------
    ParameterError
        A length that is not a whole number of samples, or non-finite float samples.
    """
    dtype = AUDIO_FORMATS[fmt]
    if len(message) % dtype.itemsize:
        raise ParameterError(f"audio: expected a whole number of {fmt} samples ({dtype.itemsize} bytes each); "
                             f"got {len(message)} bytes")
    x = np.frombuffer(message, dtype=dtype)
    if fmt == "pcm16":
        return x.astype(np.float32) / np.float32(32768.0)
    _check_finite(x)
    # a float source a little hot is clipped, as a sound card would, rather than refused
    return np.clip(x, -1.0, 1.0).astype(np.float32)


def encode_audio(samples: np.ndarray, fmt: str = "pcm16") -> bytes:
    """Mono float samples in [-1, 1] as an audio message of ``fmt``."""
    x = np.clip(np.asarray(samples, dtype=np.float32).reshape(-1), -1.0, 1.0)
    if fmt == "pcm16":
        return np.round(x * 32767.0).astype("<i2").tobytes()
    if fmt == "f32":
        return x.astype("<f4").tobytes()
    raise ParameterError(f"format: expected one of {', '.join(AUDIO_FORMATS)}; got {fmt!r}")
