"""BVH (Biovision Hierarchy) motion files: read any skeleton, write it back.

Reading
    Any hierarchy of ``ROOT``/``JOINT`` blocks with ``End Site`` leaves, any
    Euler channel order per joint and any frame time. Rotation channels are
    converted with `gesturedb.rotations.from_euler` (``Zrotation Xrotation
    Yrotation`` means ``R = Rz @ Rx @ Ry``). The root's position channels give
    `Motion.root_positions` (a root without them stays at its OFFSET).
    Position channels on other joints (some exporters write 6 channels on
    every joint) replace that joint's OFFSET, as in BVH players; a `Motion` has
    fixed bone lengths, so their mean over the clip is used, with a warning if
    they actually move.

Units
    Lengths are converted to metres. ``length_unit_m=None`` guesses the unit
    from the height of the rest skeleton (`guess_length_unit`): a standing adult
    is 1.5-2 m tall, so the first of metres, centimetres and millimetres that
    makes a skeleton with legs 0.9-2.5 m tall (one without legs 0.3-1.3 m) is
    taken, then inches (1.2-2.2 m), else the common unit nearest to 1.6 m
    (0.75 m without legs). The factor is kept in `Skeleton.length_unit_m` and
    `write_bvh` writes back in it; `describe_length_unit` says what was guessed.

Writing
    Joints are written depth first, the root with ``Xposition Yposition
    Zposition`` and its rotation channels, every other joint with three rotation
    channels in its `Skeleton.channel_orders` order. A skeleton whose joint
    order is not depth-first (SMPL-X) reads back with the joints reordered;
    names, positions and rotations are unchanged.
"""
from __future__ import annotations

import io
import math
import os
import re
import warnings

import numpy as np

from gesturedb import rotations as rot
from gesturedb.errors import InputFileError, ParameterError, echo, echo_list
from gesturedb.io.atomic import atomic_open
from gesturedb.io.joints import body_keys
from gesturedb.motion import Motion, Skeleton

__all__ = ["LENGTH_UNITS", "describe_length_unit", "guess_length_unit", "parse_length_unit", "read_bvh",
           "write_bvh"]

_CHANNEL_NAMES = {
    "xposition": ("pos", 0), "yposition": ("pos", 1), "zposition": ("pos", 2),
    "xrotation": ("rot", "X"), "yrotation": ("rot", "Y"), "zrotation": ("rot", "Z"),
}
# Printed frame times have ~6 significant digits (0.008333 for 120 fps): a frame rate
# this close to a whole number is taken to be that number.
_FPS_SNAP_REL = 2e-4

class _Joint:
    __slots__ = ("name", "parent", "offset", "channels", "line", "end_site")

    def __init__(self, name, parent, line):
        self.name = name
        self.parent = parent
        self.offset = None
        self.channels = None
        self.line = line
        self.end_site = None


# a brace, or a run of anything else that is not white space: braces may be glued to other
# tokens ("{" ... "}" on one line)
_TOKEN_RE = re.compile(r"[{}]|[^\s{}]+")


def _tokens(lines, start, stop):
    """Yield (token, line number) over the hierarchy; ROOT/JOINT names may contain spaces.

    A generator, token by token: a line declaring ten million channels is refused at its
    count, before its names are split into a list.
    """
    for i in range(start, stop):
        line = lines[i]
        head = line.split(None, 1)
        if not head:
            continue
        key = head[0].upper()
        if key in ("ROOT", "JOINT"):
            rest = head[1].strip() if len(head) > 1 else ""
            brace = rest.endswith("{")
            name = rest[:-1].strip() if brace else rest
            yield head[0], i + 1
            yield ("\0" + name), i + 1  # marked so a joint called "{" cannot confuse the parser
            if brace:
                yield "{", i + 1
            continue
        for m in _TOKEN_RE.finditer(line):
            yield m.group(), i + 1


#: deepest joint chain accepted (a human skeleton with fingers is ~10-30 deep); a limit, not a RecursionError
MAX_BVH_DEPTH = 200
#: largest |OFFSET| component accepted, in file units (1e6 m even for a file in micrometres)
MAX_BVH_OFFSET = 1e12
#: frame rates accepted from ``Frame Time`` (1 / Frame Time), Hz; `write_bvh` writes only these
MIN_FPS, MAX_FPS = 1.0, 1000.0
#: most joints accepted in a hierarchy: a body with fingers and a face rig has a few hundred
MAX_BVH_JOINTS = 10_000
#: most channels of one joint: three positions and three rotations
MAX_JOINT_CHANNELS = 6


def _tok(tok) -> str:
    """A token for a message: joint names carry a NUL mark in the token stream (see `_tokens`)."""
    return echo(tok.lstrip("\0"))


def _text(s) -> str:
    """A user string for a message, unquoted, cut to `gesturedb.errors.MAX_ECHO_CHARS`."""
    return echo_list([s])


def _parse_hierarchy(path, lines, start, stop):
    """The joints of the HIERARCHY, in file order; linear in the number of tokens."""
    toks = _tokens(lines, start, stop)

    def fail(problem, line=None):
        where = f"line {line}: " if line else ""
        raise InputFileError(path, where + problem)

    def take(expect=None, what=None):
        """Next token; ``expect`` is a token that must come, ``what`` describes what may come."""
        nxt = next(toks, None)
        if nxt is None:
            fail(f"HIERARCHY ends early (expected {expect or what or 'more'}; the file may be truncated)", stop)
        tok, ln = nxt
        if expect is not None and tok.upper() != expect.upper():
            fail(f"expected {expect!r}, got {_tok(tok)}", ln)
        return tok, ln

    def number(what):
        tok, ln = take()
        try:
            v = float(tok)
        except ValueError:
            fail(f"{what}: expected a number, got {_tok(tok)}", ln)
        if not math.isfinite(v):
            fail(f"{what}: expected a finite number, got {_tok(tok)}", ln)
        if abs(v) > MAX_BVH_OFFSET:
            # forward kinematics of such bones overflows to inf/NaN far from here; say it where it is
            fail(f"{what}: expected a length within +-{MAX_BVH_OFFSET:g} file units, got {_tok(tok)}", ln)
        return v

    joints: list[_Joint] = []
    names: set[str] = set()  # a set, not a scan of the joints: parsing stays linear in joints

    def parse_joint(parent, kw_line, depth=0):
        if depth >= MAX_BVH_DEPTH:
            fail(f"JOINT: nested more than {MAX_BVH_DEPTH} deep (MAX_BVH_DEPTH); not a body skeleton", kw_line)
        if len(joints) >= MAX_BVH_JOINTS:
            fail(f"JOINT: expected at most {MAX_BVH_JOINTS} joints (MAX_BVH_JOINTS); the hierarchy has more. "
                 "Not a body skeleton", kw_line)
        tok, ln = take()
        if not tok.startswith("\0") or not tok[1:]:
            fail("ROOT/JOINT: expected a joint name", kw_line)
        name = tok[1:]
        label = _text(name)  # names are echoed in messages; a 100 MB name must not be
        if name in names:
            fail(f"JOINT {label}: the name is used twice", ln)
        names.add(name)
        me = len(joints)
        jt = _Joint(name, parent, ln)
        joints.append(jt)
        take("{")
        while True:
            tok, ln = take(what="'}', OFFSET, CHANNELS, JOINT or End Site")
            key = tok.upper()
            if key == "}":
                break
            if key == "OFFSET":
                jt.offset = [number(f"{label} OFFSET") for _ in range(3)]
            elif key == "CHANNELS":
                n_tok, n_ln = take()
                if not n_tok.isdigit():
                    fail(f"{label} CHANNELS: expected a channel count, got {_tok(n_tok)}", n_ln)
                if len(n_tok) > 3 or int(n_tok) > MAX_JOINT_CHANNELS:
                    # refused at the count, before reading (or echoing) the names it declares
                    fail(f"{label} CHANNELS: expected 0 to {MAX_JOINT_CHANNELS} channels, got {_text(n_tok)}",
                         n_ln)
                chans = []
                for _ in range(int(n_tok)):
                    c, c_ln = take()
                    if c.lower() not in _CHANNEL_NAMES:
                        fail(f"{label} CHANNELS: expected X/Y/Z position/rotation channels, got {_tok(c)}", c_ln)
                    chans.append(c)
                kinds = [_CHANNEL_NAMES[c.lower()] for c in chans]
                rots = [a for k, a in kinds if k == "rot"]
                poss = [a for k, a in kinds if k == "pos"]
                if len(rots) not in (0, 3) or len(set(rots)) != len(rots) or \
                        len(poss) not in (0, 3) or len(set(poss)) != len(poss):
                    fail(f"{label} CHANNELS: expected 0 or 3 distinct rotation and 0 or 3 distinct position "
                         f"channels, got {' '.join(chans)}", n_ln)
                jt.channels = chans
            elif key == "JOINT":
                parse_joint(me, ln, depth + 1)
            elif key == "END":
                take("Site")
                take("{")
                take("OFFSET")
                off = [number(f"{label} End Site OFFSET") for _ in range(3)]
                take("}")
                if jt.end_site is not None:
                    fail(f"{label}: a second End Site (one per joint is supported)", ln)
                jt.end_site = off
            else:
                fail(f"{label}: expected OFFSET, CHANNELS, JOINT, End Site or '}}', got {_tok(tok)}", ln)
        if jt.offset is None:
            fail(f"{label}: no OFFSET", jt.line)
        if jt.channels is None:
            fail(f"{label}: no CHANNELS", jt.line)

    tok, ln = take("HIERARCHY")
    tok, ln = take("ROOT")
    parse_joint(-1, ln)
    extra = next(toks, None)
    if extra is not None:
        tok, ln = extra
        fail(f"expected MOTION after the root joint's closing brace, got {_tok(tok)} "
             "(only one ROOT is supported)", ln)
    return joints


_HEADER_RE = {
    "frames": re.compile(r"^\s*Frames\s*:\s*(\S+)\s*$", re.IGNORECASE),
    "frame_time": re.compile(r"^\s*Frame\s+Time\s*:\s*(\S+)\s*$", re.IGNORECASE),
}


def _motion_header(path, lines, m_line):
    """Frames and Frame Time after MOTION; returns (n_frames, frame_time, first data line index)."""
    i = m_line + 1
    found = {}
    for key in ("frames", "frame_time"):
        while i < len(lines) and not lines[i].strip():
            i += 1
        label = "Frames:" if key == "frames" else "Frame Time:"
        if i >= len(lines):
            raise InputFileError(path, f"MOTION: no '{label}' line (the file ends after line {len(lines)})")
        m = _HEADER_RE[key].match(lines[i])
        if not m:
            raise InputFileError(path, f"line {i + 1}: expected '{label} <number>', got {echo(lines[i].strip(), 60)}")
        found[key] = (m.group(1), i + 1)
        i += 1
    txt, ln = found["frames"]
    if not txt.isdigit() or int(txt) < 1:
        raise InputFileError(path, f"line {ln}: Frames: expected a positive integer, got {echo(txt)}")
    n_frames = int(txt)
    txt, ln = found["frame_time"]
    try:
        ft = float(txt)
    except ValueError:
        ft = float("nan")
    if not (math.isfinite(ft) and ft > 0):
        raise InputFileError(path, f"line {ln}: Frame Time: expected a positive number of seconds, got {echo(txt)}")
    if not MIN_FPS <= 1.0 / ft <= MAX_FPS:
        raise InputFileError(path, f"line {ln}: Frame Time: expected {1 / MAX_FPS:g} to {1 / MIN_FPS:g} s "
                                   f"({MIN_FPS:g}-{MAX_FPS:g} fps), got {txt} s ({1 / ft:.6g} fps)")
    return n_frames, ft, i


def _frame_rate(frame_time: float) -> float:
    fps = 1.0 / frame_time
    whole = round(fps)
    if whole >= 1 and abs(fps - whole) <= _FPS_SNAP_REL * whole:
        return float(whole)
    return fps


def _channel_labels(joints):
    labels = []
    for jt in joints:
        labels.extend(f"{jt.name} {c}" for c in jt.channels)
    return labels


def _diagnose_frames(path, data_lines, first_line, n_values, labels):
    """Find the first bad frame line after a fast parse failed; raises InputFileError."""
    frame = 0
    for k, line in enumerate(data_lines):
        parts = line.split()
        if not parts:
            continue
        ln = first_line + k
        if len(parts) != n_values:
            raise InputFileError(path, f"line {ln} (frame {frame}): expected {n_values} values (from CHANNELS), "
                                       f"got {len(parts)}")
        for c, p in enumerate(parts):
            try:
                float(p)
            except ValueError:
                raise InputFileError(path, f"line {ln} (frame {frame}), value {c + 1} ({_text(labels[c])}): "
                                           f"expected a number, got {echo(p, 40)}") from None
        frame += 1
    raise InputFileError(path, f"line {first_line}: frame data could not be parsed")


#: length units a BVH file may be in: name -> metres per unit (the names `--length-unit` takes)
LENGTH_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
_UNIT_WORDS = {"m": "metres", "cm": "centimetres", "mm": "millimetres", "in": "inches"}
_UNIT_ALIASES = {"metre": "m", "metres": "m", "meter": "m", "meters": "m", "centimetres": "cm", "centimeters": "cm",
                 "millimetres": "mm", "millimeters": "mm", "inch": "in", "inches": "in"}
# Plausible joint heights (lowest joint or End Site to highest), metres: a standing adult is
# 1.5-2 m tall, a joint skeleton a little less; without legs, pelvis to head is about 0.6-0.9 m.
# The common units get a wide range, inches a narrow one (they are rare in capture files).
_HEIGHT_RANGE_M = {True: (0.9, 2.5), False: (0.3, 1.3)}
_INCH_RANGE_M = {True: (1.2, 2.2), False: (0.5, 1.0)}
_HEIGHT_TYPICAL_M = {True: 1.6, False: 0.75}
_LEG_KEYS = ("_upleg", "_leg", "_foot")


def parse_length_unit(text) -> float:
    """Metres per unit from ``"cm"``, ``"inch"``, ``"m"``, ``"mm"`` or a number of metres (``"0.0254"``).

    Raises
    ------
    ParameterError
        Anything else, or a number that is not positive and finite.
    """
    key = str(text).strip().lower()
    key = _UNIT_ALIASES.get(key, key)
    if key in LENGTH_UNITS:
        return LENGTH_UNITS[key]
    try:
        v = float(key)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v > 0):
        raise ParameterError(f"length unit: expected one of {', '.join(LENGTH_UNITS)}, 'inch' or a positive number "
                             f"of metres per unit; got {echo(text)}")
    return v


def _height_units(offsets, parents, end_sites) -> float:
    """Vertical extent of the rest joints and End Sites, in the units of ``offsets``."""
    rest = np.empty_like(offsets)
    rest[0] = offsets[0]
    for j in range(1, len(parents)):
        rest[j] = rest[parents[j]] + offsets[j]
    ys = list(rest[:, 1]) + [rest[j, 1] + off[1] for j, off in end_sites.items()]
    return float(max(ys) - min(ys))


def _has_legs(names) -> bool:
    return any(k.endswith(_LEG_KEYS) for k in body_keys(names).values())


def guess_length_unit(offsets, parents, names, end_sites=None) -> float:
    """Metres per file unit of a BVH skeleton, from its height.

    Parameters
    ----------
    offsets : ndarray [shape=(J, 3)], file units
    parents : ndarray [shape=(J,)], int
    names : sequence of str [length J]
        Joint names: a skeleton with legs (``LeftUpLeg``, ``b_l_leg``,
        ``left_knee``...) is expected to be 0.9-2.5 m tall, one without 0.3-1.3 m.
    end_sites : dict of int to ndarray [shape=(3,)], optional
        End Site offsets (file units); the head's gives the top of the head.

    Returns
    -------
    float
        1.0 (metres), 0.01 (centimetres), 0.001 (millimetres) or 0.0254 (inches):
        the first of m, cm, mm that gives a plausible height, then inches, else
        the common unit nearest the typical height.
    """
    h = _height_units(np.asarray(offsets, dtype=np.float64), np.asarray(parents), end_sites or {})
    legs = _has_legs(names)
    lo, hi = _HEIGHT_RANGE_M[legs]
    common = ("m", "cm", "mm")
    for u in common:
        if lo <= h * LENGTH_UNITS[u] <= hi:
            return LENGTH_UNITS[u]
    lo, hi = _INCH_RANGE_M[legs]
    if lo <= h * LENGTH_UNITS["in"] <= hi:
        return LENGTH_UNITS["in"]
    if h <= 0:
        return 1.0
    typical = _HEIGHT_TYPICAL_M[legs]
    return LENGTH_UNITS[min(common, key=lambda u: abs(math.log(h * LENGTH_UNITS[u] / typical)))]


def describe_length_unit(skeleton) -> str:
    """What the unit of a skeleton read from BVH means for its size, for a build report.

    E.g. ``"inches (0.0254 m per unit): the skeleton is 60.6 units = 1.54 m tall
    (0.61 m in centimetres)"``.
    """
    unit = float(skeleton.length_unit_m)
    h_m = _height_units(skeleton.offsets, skeleton.parents, skeleton.end_sites)
    h_units = h_m / unit
    name = next((u for u, v in LENGTH_UNITS.items() if abs(v - unit) <= 1e-12 * v), None)
    what = f"{_UNIT_WORDS[name]} ({unit:g} m per unit)" if name else f"{unit:g} m per unit"
    others = [f"{h_units * LENGTH_UNITS[u]:.2f} m in {_UNIT_WORDS[u]}" for u in ("cm", "in", "m")
              if u != name and 0.05 <= h_units * LENGTH_UNITS[u] <= 20]
    return (f"{what}: the skeleton is {h_units:.4g} units = {h_m:.2f} m tall"
            + (f" ({', '.join(others)})" if others else ""))


def read_bvh(path, *, length_unit_m: float | None = None) -> Motion:
    """Read a BVH file into a `Motion` in metres.

    Parameters
    ----------
    path : str or os.PathLike
    length_unit_m : float or None
        Metres per file length unit (0.01 for centimetres, 0.0254 for inches).
        ``None`` guesses it from the skeleton's height (`guess_length_unit`).

    Returns
    -------
    Motion
        ``rotations (F, J, 4)`` local quaternions, ``root_positions (F, 3)``
        metres, ``fps = 1 / Frame Time`` (snapped to a whole number when the
        printed frame time is a rounded ``1 / n``). The skeleton records the
        Euler order of every joint and ``length_unit_m``.

    Raises
    ------
    InputFileError
        Unreadable file, malformed hierarchy (more than `MAX_BVH_JOINTS` joints, more
        than `MAX_JOINT_CHANNELS` channels on a joint), missing ``MOTION`` / ``Frames`` /
        ``Frame Time``, fewer or more frame lines than ``Frames:``, a frame line
        with the wrong number of values, a non-numeric or non-finite value; the
        message names the line, frame and channel.
    ParameterError
        If ``length_unit_m`` is not a positive number.
    """
    if length_unit_m is not None:
        length_unit_m = float(length_unit_m)
        if not (math.isfinite(length_unit_m) and length_unit_m > 0):
            raise ParameterError(f"length_unit_m: expected a positive number of metres per unit; got {length_unit_m}")
    try:
        # utf-8-sig: a byte-order mark (some exporters, Windows editors) is not part of "HIERARCHY"
        with open(path, "r", encoding="utf-8-sig", errors="replace") as f:
            text = f.read()
    except OSError as exc:
        raise InputFileError(path, f"cannot read: {exc.strerror or exc}") from None
    lines = text.splitlines()
    m_line = next((i for i, ln in enumerate(lines) if ln.strip().upper() == "MOTION"), None)
    if m_line is None:
        raise InputFileError(path, "no MOTION section (expected a line 'MOTION' after the HIERARCHY)")
    joints = _parse_hierarchy(path, lines, 0, m_line)
    n_frames, frame_time, first = _motion_header(path, lines, m_line)

    labels = _channel_labels(joints)
    n_values = len(labels)
    data_lines = lines[first:]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # loadtxt warns on an empty block; counted below
            data = np.loadtxt(io.StringIO("\n".join(data_lines)), dtype=np.float64, ndmin=2,
                              comments=None)
    except ValueError:
        _diagnose_frames(path, data_lines, first + 1, n_values, labels)
    if data.shape[0] == 0:
        raise InputFileError(path, f"MOTION: Frames: {n_frames} declared but there are no frame lines "
                                   "(the file is truncated)")
    if data.shape[1] != n_values:
        _diagnose_frames(path, data_lines, first + 1, n_values, labels)
    if data.shape[0] != n_frames:
        more = "more" if data.shape[0] > n_frames else "fewer"
        hint = "" if more == "more" else " (the file is truncated)"
        raise InputFileError(path, f"MOTION: Frames: {n_frames} declared but the file has {data.shape[0]} frame "
                                   f"lines ({more}){hint}")
    bad = ~np.isfinite(data)
    if bad.any():
        f, c = (int(v) for v in np.argwhere(bad)[0])
        ln = _line_of_frame(data_lines, f) + first + 1
        raise InputFileError(path, f"line {ln} (frame {f}), value {c + 1} ({_text(labels[c])}): expected a finite number, "
                                   f"got {data[f, c]}")
    return _to_motion(path, joints, data, frame_time, length_unit_m)


def _line_of_frame(data_lines, f):
    seen = -1
    for k, line in enumerate(data_lines):
        if line.strip():
            seen += 1
            if seen == f:
                return k
    return 0


def _to_motion(path, joints, data, frame_time, length_unit_m):
    n_j = len(joints)
    parents = np.array([jt.parent for jt in joints], dtype=np.int64)
    offsets = np.array([jt.offset for jt in joints], dtype=np.float64)
    n_f = data.shape[0]

    col = 0
    rot_cols = {}  # order -> (joint indices, (n, 3) column indices)
    orders = []
    pos_cols = {}
    for j, jt in enumerate(joints):
        order = ""
        rc, pc = [], [None, None, None]
        for c in jt.channels:
            kind, axis = _CHANNEL_NAMES[c.lower()]
            if kind == "rot":
                order += axis
                rc.append(col)
            else:
                pc[axis] = col
            col += 1
        orders.append(order)
        if order:
            idx, cols = rot_cols.setdefault(order, ([], []))
            idx.append(j)
            cols.append(rc)
        if pc[0] is not None:
            pos_cols[j] = pc

    if any(j != 0 for j in pos_cols):
        # non-root translations replace the OFFSET; a Motion has fixed bones, so take the mean
        scale_units = max(float(np.ptp(offsets, axis=0).max()), 1e-9)
        for j, pc in pos_cols.items():
            if j == 0:
                continue
            vals = data[:, pc]
            offsets[j] = vals.mean(axis=0)
            spread = float(np.abs(vals - offsets[j]).max())
            if spread > 1e-3 * scale_units:
                warnings.warn(f"{os.fspath(path)}: joint {_text(joints[j].name)} has position channels that move by up to "
                              f"{spread:.4g} file units; bone lengths are fixed, so their mean is used",
                              stacklevel=3)

    ends_file = {j: np.asarray(jt.end_site, dtype=np.float64) for j, jt in enumerate(joints) if jt.end_site is not None}
    if length_unit_m is None:
        unit = guess_length_unit(offsets, parents, [jt.name for jt in joints], ends_file)
    else:
        unit = length_unit_m

    rotations = np.empty((n_f, n_j, 4))
    rotations[..., 0] = 1.0
    rotations[..., 1:] = 0.0
    for order, (idx, cols) in rot_cols.items():
        angles = data[:, np.asarray(cols)]  # (F, n, 3)
        rotations[:, idx] = rot.from_euler(angles, order)

    if 0 in pos_cols:
        root = data[:, pos_cols[0]] * unit
    else:
        root = np.repeat(offsets[:1] * unit, n_f, axis=0)

    ends = {j: off * unit for j, off in ends_file.items()}
    skel = Skeleton([jt.name for jt in joints], parents, offsets * unit, orders, ends, unit)
    return Motion(skel, _frame_rate(frame_time), rotations, root)


def _fmt(v) -> str:
    # %.6f keeps 1e-6 file units / degrees, far below the 1e-4 round-trip budget
    return " ".join(f"{x + 0.0:.6f}" for x in v)


def write_bvh(path, motion: Motion, *, length_unit_m: float | None = None) -> None:
    """Write a `Motion` to a BVH file.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; written to a temporary file in the same folder and
        renamed, so a failure never leaves half a file.
    motion : Motion
    length_unit_m : float or None
        Metres per written length unit; ``None`` uses
        ``motion.skeleton.length_unit_m`` (the unit the skeleton was read in).

    Notes
    -----
    The root gets ``Xposition Yposition Zposition`` then its rotation
    channels; every other joint its rotation channels in
    ``skeleton.channel_orders`` order. A joint with order ``""`` is written
    with ``CHANNELS 0`` and must not rotate. Angles are printed in degrees,
    lengths with 6 decimals.

    Raises
    ------
    ParameterError
        Bad ``length_unit_m``, a frame rate outside `MIN_FPS` to `MAX_FPS` (the range
        `read_bvh` accepts), or a rotating joint without rotation channels.
    InputFileError
        If the file cannot be written.
    """
    if not isinstance(motion, Motion):
        raise ParameterError(f"motion: expected a Motion; got {type(motion).__name__}")
    sk = motion.skeleton
    unit = sk.length_unit_m if length_unit_m is None else float(length_unit_m)
    if not (math.isfinite(unit) and unit > 0):
        raise ParameterError(f"length_unit_m: expected a positive number of metres per unit; got {length_unit_m}")
    inv = 1.0 / unit
    if not MIN_FPS <= motion.fps <= MAX_FPS:
        # read_bvh refuses such a Frame Time: never write a file our own reader cannot read back
        raise ParameterError(f"motion.fps: expected {MIN_FPS:g} to {MAX_FPS:g} frames per second for BVH "
                             f"(read_bvh's range); got {motion.fps:g}")

    orders = list(sk.channel_orders)
    if not orders[0]:
        orders[0] = "ZXY"  # the root always gets 6 channels so it can turn
    for j, order in enumerate(orders):
        if not order and rot.angle_between(motion.rotations[:, j], rot.identity()).max() > 1e-6:
            raise ParameterError(f"joint {_text(sk.names[j])} has no rotation channels (channel order '') but rotates; "
                                 "set skeleton.channel_orders for it")

    out = ["HIERARCHY"]
    written = []  # joint indices in file order: the frame columns must follow it
    children = [[] for _ in range(sk.n_joints)]
    for j in range(1, sk.n_joints):
        children[sk.parents[j]].append(j)
    # depth-first, children in index order; an explicit stack keeps deep chains (fingers) off the recursion limit
    stack = [(0, 0, False)]
    while stack:
        j, depth, closing = stack.pop()
        ind = "\t" * depth
        if closing:
            out.append(ind + "}")
            continue
        written.append(j)
        out.append(f"{ind}{'ROOT' if j == 0 else 'JOINT'} {sk.names[j]}")
        out.append(ind + "{")
        out.append(f"{ind}\tOFFSET {_fmt(sk.offsets[j] * inv)}")
        axes = " ".join(f"{a}rotation" for a in orders[j])
        if j == 0:
            out.append(f"{ind}\tCHANNELS 6 Xposition Yposition Zposition {axes}")
        else:
            out.append(f"{ind}\tCHANNELS {len(orders[j])} {axes}".rstrip())
        if j in sk.end_sites:
            out += [f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {_fmt(sk.end_sites[j] * inv)}", f"{ind}\t}}"]
        stack.append((j, depth, True))
        for c in reversed(children[j]):
            stack.append((c, depth + 1, False))

    columns = [motion.root_positions * inv]
    columns += [rot.to_euler(motion.rotations[:, j], orders[j]) for j in written if orders[j]]
    data = np.concatenate(columns, axis=1)
    out += ["MOTION", f"Frames: {motion.n_frames}", f"Frame Time: {1.0 / motion.fps:.10g}"]

    # a failed write never leaves half a BVH
    with atomic_open(path, "w", newline="\n") as f:
        f.write("\n".join(out) + "\n")
        # "+ 0.0" folds -0.0 to 0.0 so untouched channels do not print as -0.000000
        np.savetxt(f, data + 0.0, fmt="%.6f", delimiter=" ")
