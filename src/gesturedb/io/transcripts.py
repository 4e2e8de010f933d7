"""Word timings: Praat TextGrid, GENEA TSV and JSON transcripts -> `Words`.

Every reader normalises the text the same way: lower case, punctuation removed
(an apostrophe inside a word stays: ``don't``), whitespace collapsed. Intervals
that are then empty or mark silence (``""``, ``<sil>``, ``sil``, ``sp``,
``spn``) are dropped. An interval holding several words (GENEA writes
``"there is"``) stays one entry, since its words have no timings of their own.
"""
from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass

import numpy as np

from gesturedb.errors import GestureDBWarning, InputFileError, ParameterError
from gesturedb.io.text import read_text_lines

__all__ = ["FIT_TOLERANCE_S", "Words", "check_words_fit", "read_genea_tsv", "read_json_words", "read_textgrid",
           "read_transcript", "normalize_word"]

_SILENCE = frozenset({"sil", "sp", "spn", "sil>", "<sil>", "<sp>", "<spn>", "<p:>", "#"})
_PUNCT = re.compile(r"[^\w\s']|_")
_LOOSE_APOSTROPHE = re.compile(r"(?<!\w)'|'(?!\w)")
_SPACES = re.compile(r"\s+")


def normalize_word(text: str) -> str:
    """Lower-case ``text`` and strip punctuation; ``""`` for silence markers.

    Parameters
    ----------
    text : str

    Returns
    -------
    str
        E.g. ``"Yeah,"`` -> ``"yeah"``, ``"It is-"`` -> ``"it is"``,
        ``"Don't"`` -> ``"don't"``, ``"<sil>"`` / ``"(?)"`` -> ``""``.
    """
    t = text.strip().lower()
    if t in _SILENCE:
        return ""
    t = _PUNCT.sub("", t.replace("\u2019", "'"))
    t = _LOOSE_APOSTROPHE.sub("", t)
    t = _SPACES.sub(" ", t).strip()
    return "" if t in _SILENCE else t


@dataclass(eq=False)
class Words:
    """Timed words of one recording.

    Parameters
    ----------
    start_s, end_s : ndarray [shape=(W,)], float64, seconds
        Interval of each word; ``start_s <= end_s`` and starts never decrease.
    text : list of str [length W]
        Normalised words (see `normalize_word`).
    source : str or None
        The file the words came from.
    duration_s : float or None
        Length of the speech the timings were made for, seconds, where the file
        says (a TextGrid's ``xmax``); None for TSV and JSON, and for a selection
        of words (slicing drops it: a selection no longer claims to be the
        whole transcript of that speech).
    accept_mismatch : bool
        Use these words with speech they do not fit (`check_words_fit` warns
        instead of refusing them); ``read_transcript(..., accept_mismatch=True)``,
        ``gesturedb synth --accept-transcript-mismatch``. Kept by slicing.

    Raises
    ------
    ParameterError
        On mismatched lengths, non-finite times, an end before its start or
        starts out of order.
    """

    start_s: np.ndarray
    end_s: np.ndarray
    text: list
    source: str | None = None
    duration_s: float | None = None
    accept_mismatch: bool = False

    def __post_init__(self):
        self.start_s = np.asarray(self.start_s, dtype=np.float64).reshape(-1)
        self.end_s = np.asarray(self.end_s, dtype=np.float64).reshape(-1)
        self.text = [str(t) for t in self.text]
        if self.source is not None:
            self.source = os.fspath(self.source)
        problem = _check_times(self.start_s, self.end_s, self.text)
        if problem:
            where = f"{self.source}: " if self.source else ""
            raise ParameterError(f"Words: {where}{problem[1]}")

    def __len__(self) -> int:
        return len(self.text)

    def __getitem__(self, item) -> "Words":
        """Words by slice, boolean mask or index array (an int gives a one-word `Words`)."""
        if isinstance(item, (int, np.integer)):
            n = len(self)
            if not -n <= item < n:
                raise IndexError(f"word {item} out of range for {n} words")
            item = slice(item % n, item % n + 1)
        if isinstance(item, slice):
            return Words(self.start_s[item], self.end_s[item], self.text[item], self.source,
                         accept_mismatch=self.accept_mismatch)
        idx = np.asarray(item)
        if idx.dtype == bool:
            if idx.shape != (len(self),):
                raise ParameterError(f"Words[mask]: expected a boolean mask of shape ({len(self)},); got {idx.shape}")
            idx = np.flatnonzero(idx)
        elif not np.issubdtype(idx.dtype, np.integer) or idx.ndim != 1:
            raise ParameterError(f"Words[...]: expected a slice, int, boolean mask or 1-d int array; got {item!r}")
        return Words(self.start_s[idx], self.end_s[idx], [self.text[i] for i in idx], self.source,
                     accept_mismatch=self.accept_mismatch)

    def __iter__(self):
        """Iterate over ``(start_s, end_s, text)`` tuples."""
        return iter(zip(self.start_s.tolist(), self.end_s.tolist(), self.text))

    @property
    def onsets(self) -> np.ndarray:
        """Word onset times, ``(W,)`` seconds (the same array as `start_s`)."""
        return self.start_s

    def between(self, t0_s: float, t1_s: float) -> "Words":
        """The words whose onset lies in ``[t0_s, t1_s)``."""
        lo, hi = np.searchsorted(self.start_s, [t0_s, t1_s], side="left")
        return self[int(lo):int(hi)]


def _check_times(start, end, text) -> tuple[int, str] | None:
    """(index of the first bad word, description), or None when the times are fine."""
    if not (start.shape == end.shape == (len(text),)):
        return 0, f"start_s, end_s and text must have one entry per word; got {start.shape}, {end.shape}, {len(text)}"
    bad = ~(np.isfinite(start) & np.isfinite(end))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        return i, f"word {i} ({text[i]!r}): times must be finite; got start {start[i]}, end {end[i]}"
    bad = end < start
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        return i, f"word {i} ({text[i]!r}): end {end[i]} s is before start {start[i]} s"
    bad = np.diff(start) < 0
    if bad.any():
        i = int(np.flatnonzero(bad)[0]) + 1
        return i, f"word {i} ({text[i]!r}): starts at {start[i]} s, before word {i - 1} ({text[i - 1]!r}) at " \
               f"{start[i - 1]} s; expected non-decreasing start times"
    return None


def _build(path, rows, duration_s: float | None = None) -> Words:
    """rows: (start, end, raw text, where) -> validated Words; ``where`` names the line/entry for errors.

    Besides what :class:`Words` checks (finite, end not before start, starts in order), a
    transcript's times must not be negative: a word before the start of its speech has no
    frames, and keyword stretches and the graph's word clips computed from one came out of
    negative length (``-58269 frames``) and failed the synthesis much later.
    """
    kept = [(s, e, normalize_word(t), w) for s, e, t, w in rows]
    kept = [r for r in kept if r[2]]
    for s, e, t, where in kept:
        for field, v in (("start", s), ("end", e)):
            if not v >= 0:  # also NaN
                raise InputFileError(path, f"{where}: {field}: expected a time >= 0 s for word {t!r}, got {v!r}")
    start = np.array([r[0] for r in kept], dtype=np.float64)
    end = np.array([r[1] for r in kept], dtype=np.float64)
    text = [r[2] for r in kept]
    problem = _check_times(start, end, text)
    if problem:
        i, msg = problem
        raise InputFileError(path, f"{kept[i][3]}: {msg}")
    return Words(start, end, text, os.fspath(path), duration_s)


def read_textgrid(path, *, tier: str = "words") -> Words:
    """Read the word tier of a Praat TextGrid.

    Parameters
    ----------
    path : str or os.PathLike
    tier : str
        Tier name, matched case-insensitively.

    Returns
    -------
    Words

    Raises
    ------
    InputFileError
        Unreadable file, no such tier (the message lists the tiers), a point
        tier, or bad times.
    """
    from praatio import textgrid
    from praatio.utilities import errors as praat_errors

    if not os.path.isfile(path):
        raise InputFileError(path, "no such file")
    try:
        tg = textgrid.openTextgrid(os.fspath(path), includeEmptyIntervals=False, reportingMode="silence")
    except (praat_errors.PraatioException, ValueError, IndexError, KeyError, UnicodeError, AttributeError,
            TypeError) as exc:
        bad = _textgrid_problem(path)
        if bad:  # praatio says "Expected field in Textgrid missing" for a negative time: name the line instead
            raise InputFileError(path, bad) from None
        # praatio's messages span lines: keep one
        raise InputFileError(path, f"cannot parse as a Praat TextGrid: {type(exc).__name__}: "
                                   f"{' '.join(str(exc).split())}") from None
    names = list(tg.tierNames)
    match = [n for n in names if n.strip().lower() == tier.lower()]
    if not match:
        raise InputFileError(path, f"no tier named {tier!r} (case-insensitive); tiers: "
                                   f"{', '.join(repr(n) for n in names) or 'none'}")
    t = tg.getTier(match[0])
    if not isinstance(t, textgrid.IntervalTier):
        raise InputFileError(path, f"tier {match[0]!r}: expected an interval tier, got a point tier")
    rows = [(e.start, e.end, e.label, f"tier {match[0]!r} interval {k + 1}") for k, e in enumerate(t.entries)]
    # xmin..xmax: the stretch of speech the TextGrid was made for (Praat and aligners write the audio's length)
    span = float(tg.maxTimestamp) - float(tg.minTimestamp)
    return _build(path, rows, span if math.isfinite(span) and span > 0 else None)


_TEXTGRID_TIME = re.compile(r"\s*(xmin|xmax|number)\s*=\s*(\S+)\s*$")


def _textgrid_problem(path) -> str | None:
    """A missing Praat header, or the first negative, non-finite or reversed time of a (long-format)
    TextGrid, naming its line.

    Only called once praatio has refused the file, to say where and why in the words of
    the other readers (praatio's own message for a file that is not a TextGrid at all is an
    IndexError).
    """
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError:
        return None
    # Praat writes UTF-16 with a byte-order mark where the text is not ASCII
    utf16 = raw.startswith((b"\xff\xfe", b"\xfe\xff"))
    lines = raw.decode("utf-16" if utf16 else "utf-8-sig", errors="replace").splitlines()
    first = next(((k, ln.strip()) for k, ln in enumerate(lines, start=1) if ln.strip()), None)
    if first is None:
        return "empty file; expected a Praat TextGrid"
    if not first[1].replace(" ", "").startswith(("Filetype=", "Filetype\t")) or "ooTextFile" not in first[1]:
        return (f"line {first[0]}: expected the Praat header 'File type = \"ooTextFile\"' "
                f"(a TextGrid saved as text); got {first[1][:60]!r}")
    xmin = None
    for k, line in enumerate(lines, start=1):
        m = _TEXTGRID_TIME.match(line)
        if m is None:
            continue
        field, txt = m.groups()
        try:
            v = float(txt)
        except ValueError:
            return f"line {k}: {field}: expected a number of seconds, got {txt!r}"
        if not math.isfinite(v) or v < 0:
            return f"line {k}: {field}: expected a finite time >= 0 s, got {txt!r}"
        if field == "xmax" and xmin is not None and v < xmin[1]:
            return f"line {k}: xmax {v:g} s is before xmin {xmin[1]:g} s (line {xmin[0]})"
        xmin = (k, v) if field == "xmin" else None
    return None


def _number(path, txt, where, field):
    try:
        v = float(txt)
    except ValueError:
        raise InputFileError(path, f"{where}: {field}: expected a number of seconds, got {txt!r}") from None
    if not math.isfinite(v):
        raise InputFileError(path, f"{where}: {field}: expected a finite number of seconds, got {txt!r}")
    return v


def read_genea_tsv(path) -> Words:
    """Read a GENEA Challenge transcript: ``start<TAB>end<TAB>word`` per line.

    GENEA's files have no header; a first line naming the columns (``start``/``start_s``/``begin``,
    ``end``/``end_s``/``stop``, then the word's column), as spreadsheets and pandas write, is skipped.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    Words

    Raises
    ------
    InputFileError
        Unreadable file, a line without three fields, a non-numeric time, or
        bad times; the message names the line.
    """
    lines = read_text_lines(path)
    rows = []
    first = True
    for k, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        parts = line.split("\t") if "\t" in line else line.split(None, 2)
        if len(parts) < 3:
            raise InputFileError(path, f"line {k}: expected start<TAB>end<TAB>word, got {line.strip()[:60]!r}")
        if first and _is_header(parts):  # a spreadsheet's or pandas' export names its columns
            first = False
            continue
        first = False
        where = f"line {k}"
        s = _number(path, parts[0].strip(), where, "start")
        e = _number(path, parts[1].strip(), where, "end")
        rows.append((s, e, " ".join(p.strip() for p in parts[2:]), where))
    return _build(path, rows)


_JSON_KEYS = {"start": ("start", "start_s", "begin"), "end": ("end", "end_s", "stop"), "word": ("word", "text")}


def _is_header(parts: list[str]) -> bool:
    """Whether a TSV line names the columns (``start end word``, or the JSON reader's other names)."""
    return parts[0].strip().lower() in _JSON_KEYS["start"] and parts[1].strip().lower() in _JSON_KEYS["end"]


#: largest JSON transcript read (an hour of words is ~1 MB)
MAX_TRANSCRIPT_BYTES = 64 * 2**20


def read_json_words(path) -> Words:
    """Read word timings from JSON.

    The file holds ``{"words": [{"start": s, "end": e, "word": w}, ...]}`` or
    the list alone; ``start_s``/``end_s`` and ``text`` are accepted too.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    Words

    Raises
    ------
    InputFileError
        Invalid JSON, an unexpected layout, a missing key or a bad time; the
        message names the entry and key.
    """
    try:
        size = os.path.getsize(path)
        if size > MAX_TRANSCRIPT_BYTES:
            raise InputFileError(path, f"expected a transcript of at most {MAX_TRANSCRIPT_BYTES} bytes "
                                       f"(MAX_TRANSCRIPT_BYTES), got {size}")
        with open(path, "r", encoding="utf-8-sig") as f:
            doc = json.load(f)
    except (OSError, UnicodeError) as exc:
        raise InputFileError(path, f"cannot read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    except RecursionError:
        raise InputFileError(path, "invalid JSON: nested too deeply (more than Python's recursion limit)") from None
    except ValueError as exc:  # e.g. a number of more than 4300 digits
        raise InputFileError(path, f"invalid JSON: {str(exc).splitlines()[0]}") from None
    items = doc.get("words") if isinstance(doc, dict) else doc
    if not isinstance(items, list):
        raise InputFileError(path, "expected {\"words\": [{\"start\": s, \"end\": e, \"word\": w}, ...]} or a list "
                                   f"of such objects; got {type(doc).__name__}"
                                   + (f" with keys {', '.join(map(str, doc))}" if isinstance(doc, dict) else ""))
    rows = []
    for k, item in enumerate(items):
        where = f"words[{k}]"
        if not isinstance(item, dict):
            raise InputFileError(path, f"{where}: expected an object with start, end and word; got {item!r:.60}")
        vals = {}
        for field, keys in _JSON_KEYS.items():
            key = next((x for x in keys if x in item), None)
            if key is None:
                raise InputFileError(path, f"{where}: missing {field!r} (accepted keys: {', '.join(keys)}); "
                                           f"got keys {', '.join(map(str, item))}")
            vals[field] = item[key]
        if not isinstance(vals["word"], str):
            raise InputFileError(path, f"{where}: word: expected a string, got {vals['word']!r}")
        for field in ("start", "end"):
            v = vals[field]
            if isinstance(v, bool) or not isinstance(v, (int, float, str)):
                raise InputFileError(path, f"{where}: {field}: expected a number of seconds, got {v!r}")
            vals[field] = _number(path, str(v), where, field)
        rows.append((vals["start"], vals["end"], vals["word"], where))
    return _build(path, rows)


_READERS = {".textgrid": read_textgrid, ".tsv": read_genea_tsv, ".json": read_json_words}


#: How far (s) a transcript's times may disagree with its audio before the transcript counts as
#: another recording's: a word may start this long after the audio's end, and a TextGrid's declared
#: length (``xmax``) may differ from the audio's by this much. Transcripts write times to
#: milliseconds or centiseconds and forced aligners step in 10 ms frames; 0.1 s covers that
#: rounding (the BEAT2 TextGrids declare their audio's length to the sample) and is less than half a
#: median word (0.20-0.28 s in the BEAT2 and GENEA transcripts of ../shared/data).
FIT_TOLERANCE_S = 0.1


def check_words_fit(words: Words, duration_s: float, *, audio=None, accept_mismatch: bool | None = None) -> None:
    """Refuse word timings that do not belong to speech of ``duration_s`` seconds.

    A transcript of another file, or of a longer take, silently shifts every keyword
    step. The words do not fit the speech when

    - a word starts more than `FIT_TOLERANCE_S` after the speech ends (the transcript
      times speech the audio does not have), or
    - the transcript declares the length of the speech it was made for (a TextGrid's
      ``xmax``, `Words.duration_s`) and it differs from ``duration_s`` by more than
      `FIT_TOLERANCE_S` (a transcript of a shorter recording has all its words inside).

    The last word may end past the speech (audio cut mid-word). With ``accept_mismatch``
    the same message is a :class:`gesturedb.errors.GestureDBWarning` and the words that
    start inside the speech are used. A transcript with no word starting inside the
    speech is refused either way: it has nothing to use.

    Parameters
    ----------
    words : Words
    duration_s : float
        Length of the speech, seconds.
    audio : str, optional
        The speech file, for the messages.
    accept_mismatch : bool, optional
        Use the words anyway (default: ``words.accept_mismatch``, set by
        ``read_transcript(..., accept_mismatch=True)``).

    Raises
    ------
    InputFileError
        Naming the transcript, the audio, the transcript's end (or declared length) and
        the audio's length, unless the mismatch is accepted.
    """
    import warnings

    if len(words) == 0:
        return
    if accept_mismatch is None:
        accept_mismatch = words.accept_mismatch
    where = words.source or "transcript"
    of = f" ({audio})" if audio else ""
    first, last = float(words.start_s.min()), float(words.end_s.max())
    if first >= duration_s:
        raise InputFileError(where, f"words: expected words inside the audio{of}, which lasts {duration_s:.2f} s; "
                                    f"got {len(words)} words from {first:.2f} to {last:.2f} s (another file's transcript?)")
    problems = []
    late = int((words.start_s > duration_s + FIT_TOLERANCE_S).sum())
    if late:
        problems.append(f"the transcript ends at {last:.2f} s, the audio is {duration_s:.2f} s long: {late} of "
                        f"{len(words)} words start more than {FIT_TOLERANCE_S:g} s after its end")
    declared = words.duration_s
    if declared is not None and abs(declared - duration_s) > FIT_TOLERANCE_S:
        problems.append(f"the transcript was made for {declared:.2f} s of speech (its xmax), the audio is "
                        f"{duration_s:.2f} s long")
    if not problems:
        return
    text = f"does not fit the audio{of}: {'; '.join(problems)}"
    if not accept_mismatch:
        raise InputFileError(where, f"{text}. A transcript of another recording? To use it anyway pass "
                                    "--accept-transcript-mismatch (accept_mismatch=True)")
    ignored = "; words that start after the audio's end are ignored" if late else ""
    warnings.warn(GestureDBWarning(f"{where}: {text} (accepted{ignored})"), stacklevel=2)


def read_transcript(path, *, accept_mismatch: bool = False) -> Words:
    """Read word timings, choosing the reader by extension.

    ``.TextGrid`` -> `read_textgrid` (tier ``words``), ``.tsv`` ->
    `read_genea_tsv`, ``.json`` -> `read_json_words` (case-insensitive).

    Parameters
    ----------
    path : str or os.PathLike
    accept_mismatch : bool
        Mark the words to be used even with speech they do not fit
        (`check_words_fit` then warns instead of refusing them).

    Returns
    -------
    Words

    Raises
    ------
    InputFileError
        Unknown extension or any reader's error.
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    reader = _READERS.get(ext)
    if reader is None:
        raise InputFileError(path, f"unknown transcript extension {ext or '(none)'!r}; expected .TextGrid, .tsv "
                                   "or .json")
    words = reader(path)
    words.accept_mismatch = bool(accept_mismatch)
    return words
