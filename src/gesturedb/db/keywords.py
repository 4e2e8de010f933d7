"""Keyword sub-databases (Habibie et al. 2022, Sec. 4.2).

"Produce a specific body gesture whenever a specific keyword is detected in the
speech ... the gesture is selected from a separate database containing gestures
semantically correlated with the keyword." A *sub-database* is named after its
keyword and holds every stretch of the database where the speaker said that
word: the word itself, ``before_s`` before it and ``after_s`` after it, clipped
to its recording. During synthesis, every search step whose output frames
overlap the keyword in the input transcript may only take windows from those
stretches (:func:`keyword_step_masks`); the other steps search the whole
database.

Storage (one group per keyword, the name in lower case)::

    subdatabases/<word>/start       int64  (n,)  first database frame of each stretch
    subdatabases/<word>/length      int64  (n,)  stretch length, frames
    subdatabases/<word>/recording   int32  (n,)  index into recordings/
    subdatabases/<word>/word_index  int64  (n,)  the occurrence's index into words/
    subdatabases/<word>/mask        uint64 (B,)  union of the stretches as a packed bitset
                                                 over database frames (bit f & 63 of word f >> 6)
    attrs: definition (JSON: word, before_s, after_s, matched, found, skipped, removed)

Matching. Words are compared after the project's normalisation
(:func:`gesturedb.io.transcripts.normalize_word`: lower case, punctuation
stripped) and as whole words: ``hand`` matches ``Hand,`` but not ``handle``; an
entry that holds several words (GENEA writes ``"there is"``) matches each of
them, with the entry's timing.

Times and frames. Database frame ``i`` of a recording covers
``[i / fps, (i + 1) / fps)`` seconds (as in :mod:`gesturedb.features.audio`), so
a time interval ``[a, b)`` covers frames ``floor(a * fps)`` to
``ceil(b * fps) - 1`` and always at least one frame (a zero-length word still
covers the frame it is said in). The same rule turns the input transcript's
words into output frames.

Searching. The search allows a window when its first and last frames are in
the mask (``../shared/spec/search.md``), so where two stretches of one recording
lie less than a window apart, a window may start in one and end in the next,
passing through the few frames between them. With the default context (0.5 s
before, 1 s after) such neighbours are one stretch of speech about the keyword
anyway.

Edits (:func:`add_keyword`, :func:`add_keywords`, :func:`remove_occurrence`,
:func:`drop_keyword`) go through :func:`gesturedb.db.storage.edit`: a failed edit
leaves the file as it was. Each reads what it decides from (the words table, the
sub-databases there are) while holding the database's write lock, so two
concurrent edits act as if run one after the other (the second is refused if it
would be refused then). Many keywords go in one edit (:func:`add_keywords`, or
``gesturedb keywords DB add W1 W2 ...`` / ``--from FILE``): the file is copied
once, not once per word.
:func:`gesturedb.db.export.export_keyword` writes a sub-database as a complete database of its own.
"""
from __future__ import annotations

import difflib
import math
import os
from collections import Counter
from typing import NamedTuple, Sequence

import numpy as np

from gesturedb import control
from gesturedb.db import schema, storage, store
from gesturedb.db.database import Database
from gesturedb.db.subdatabase import SUBDB_FIELDS, SubDatabase, time_to_frames  # noqa: F401 (re-exported)
from gesturedb.db.subdatabase import mask_of as _mask_of
from gesturedb.db.subdatabase import read_all as _read_all
from gesturedb.db.subdatabase import read_subdb as _read_subdb
from gesturedb.db.subdatabase import write_subdb as _write_subdb
from gesturedb.errors import InputFileError, ParameterError, echo, echo_list
from gesturedb.io import read_transcript
from gesturedb.io.text import read_text_lines
from gesturedb.io.transcripts import normalize_word

__all__ = [
    "SubDatabase",
    "WordCount",
    "Occurrence",
    "subdatabases",
    "get_subdatabase",
    "find_occurrences",
    "add_keyword",
    "add_keywords",
    "KeywordAdded",
    "read_word_list",
    "remove_occurrence",
    "drop_keyword",
    "list_words",
    "show",
    "keyword_step_masks",
    "normalise_word",
]

def normalise_word(text: str) -> str:
    """The project's word normalisation (:func:`gesturedb.io.transcripts.normalize_word`).

    Lower case, punctuation stripped except an apostrophe inside a word,
    ``""`` for silence markers: ``"Hand,"`` -> ``"hand"``.
    """

    return normalize_word(str(text))


def _tokens(text: str) -> list[str]:
    """The whole words of a transcript entry (GENEA keeps ``"there is"`` as one timed entry)."""
    return normalise_word(text).split()


def _keyword_name(word) -> str:
    """Validate what a caller gave as a keyword and return its sub-database name."""
    if not isinstance(word, str):
        raise ParameterError(f"keyword: expected a word (str), got {type(word).__name__} {echo(word)}")
    w = normalise_word(word)
    if not w:
        raise ParameterError(
            f"keyword: expected a word with at least one letter or digit (not a silence marker), got {echo(word)}"
        )
    if any(c.isspace() for c in w):
        raise ParameterError(
            f"keyword: expected a single word (sub-databases match whole words of the transcript), got {echo(word)}"
        )
    if "/" in w or w == ".":
        raise ParameterError(f"keyword: expected a word without '/', got {echo(word)}")
    return w


def _check_seconds(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name}: expected a non-negative number of seconds, got {value!r}") from None
    if isinstance(value, bool) or not (math.isfinite(v) and v >= 0):
        raise ParameterError(f"{name}: expected a non-negative number of seconds, got {value!r}")
    return v


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ParameterError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


# --------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------

def subdatabases(db) -> dict[str, SubDatabase]:
    """Every keyword sub-database of an open database.

    Parameters
    ----------
    db : gesturedb.db.database.Database

    Returns
    -------
    dict of str to SubDatabase
        Keyword -> sub-database, sorted by keyword. Read from the file on every
        call (edits replace the file, so reopen the database to see them).
    """
    return _read_all(db.h5, db.path)


def get_subdatabase(db, word: str) -> SubDatabase:
    """One sub-database; the error lists the keywords there are and close ones."""
    w = _keyword_name(word)
    subs = subdatabases(db)
    if w not in subs:
        raise ParameterError(_missing_message(w, list(subs), db.path))
    return subs[w]


def _missing_message(w: str, existing: list[str], path: str) -> str:
    if not existing:
        return f"keyword {echo(w)}: {path} has no keyword sub-databases (add one with `gesturedb keywords {path} add WORD`)"
    close = difflib.get_close_matches(w, existing, n=3)
    hint = f"; did you mean {', '.join(map(repr, close))}?" if close else ""
    return f"keyword {echo(w)}: no such sub-database in {path}; keywords: {echo_list(existing)}{hint}"


# --------------------------------------------------------------------------
# finding occurrences
# --------------------------------------------------------------------------

class _Tables(NamedTuple):
    """What finding occurrences needs from a database (read once, closed after)."""

    path: str
    fps: float
    n_frames: int
    rec_names: list
    rec_start: np.ndarray
    rec_n: np.ndarray
    w_rec: np.ndarray
    w_start: np.ndarray
    w_end: np.ndarray
    w_text: list


def _tables(db) -> _Tables:
    recs = db.recordings
    w = db.words
    return _Tables(
        path=db.path, fps=db.fps, n_frames=db.n_frames,
        rec_names=[r.name for r in recs],
        rec_start=np.array([r.start_frame for r in recs], dtype=np.int64),
        rec_n=np.array([r.n_frames for r in recs], dtype=np.int64),
        w_rec=np.asarray(w.recording), w_start=np.asarray(w.start_s, dtype=np.float64),
        w_end=np.asarray(w.end_s, dtype=np.float64), w_text=list(w.text),
    )


def _unknown_word_message(w: str, t: _Tables) -> str:
    if not t.w_text:
        return (f"keyword {echo(w)}: {t.path} has no words (it was built without transcripts), "
                "so no keyword can be found in it")
    vocab = Counter(tok for x in t.w_text for tok in _tokens(x))
    close = difflib.get_close_matches(w, list(vocab), n=5, cutoff=0.6)
    hint = (f"; close words: {', '.join(f'{c!r} ({vocab[c]}x)' for c in close)}" if close
            else f"; the most frequent words are {', '.join(repr(x) for x, _ in vocab.most_common(8))}")
    return f"keyword {echo(w)}: not among the {len(t.w_text)} words of {t.path}{hint}"


def find_occurrences(db, word: str, *, before_s: float = 0.5, after_s: float = 1.0) -> SubDatabase:
    """Collect every occurrence of a word in a database's words (does not write anything).

    Parameters
    ----------
    db : gesturedb.db.database.Database
    word : str
        Matched case-insensitively against whole words of the words table.
    before_s, after_s : float >= 0, seconds
        Context kept before the word's start and after its end.

    Returns
    -------
    SubDatabase
        Stretches ``[start - before_s, end + after_s]`` in frames (see the module
        notes), clipped to the recording, in words-table order. Occurrences that
        start after the recording's last frame (a transcript longer than the
        motion) are skipped and counted in ``definition["skipped"]``.

    Raises
    ------
    ParameterError
        The word never occurs; the message suggests close words.
    """
    return _occurrences(_tables(db), _keyword_name(word), _check_seconds("before_s", before_s),
                        _check_seconds("after_s", after_s))


def _token_index(t: _Tables) -> dict[str, list[int]]:
    """Whole word -> indices of the words-table entries holding it (one pass for any number of keywords)."""
    index: dict[str, list[int]] = {}
    for i, x in enumerate(t.w_text):
        for tok in dict.fromkeys(_tokens(x)):
            index.setdefault(tok, []).append(i)
    return index


def _occurrences(t: _Tables, w: str, before_s: float, after_s: float, *, index: dict | None = None,
                 with_mask: bool = True) -> SubDatabase:
    if index is None:
        idx = np.array([i for i, x in enumerate(t.w_text) if w in _tokens(x)], dtype=np.int64)
    else:
        idx = np.asarray(index.get(w, []), dtype=np.int64)
    if idx.size == 0:
        raise ParameterError(_unknown_word_message(w, t))
    rec = t.w_rec[idx].astype(np.int64)
    ws, we = t.w_start[idx], t.w_end[idx]
    word_first, word_stop = time_to_frames(ws, we, t.fps)
    ctx_first, ctx_stop = time_to_frames(ws - before_s, we + after_s, t.fps)
    # the word's own frames are always inside its stretch, whatever the rounding
    first = np.clip(np.minimum(ctx_first, word_first), 0, None)
    stop = np.minimum(np.maximum(ctx_stop, word_stop), t.rec_n[rec])
    # a word must overlap its recording's motion: one starting after its end (a transcript longer
    # than the motion) or ending before frame 0 (negative times, which readers now refuse but an
    # older database may hold) has no gesture, and would give a stretch of negative length
    keep = (word_first < t.rec_n[rec]) & (word_stop > 0)
    start = (t.rec_start[rec] + first)[keep].astype(np.int64)
    length = (stop - first)[keep].astype(np.int64)
    definition = {
        "word": w,
        "before_s": before_s,
        "after_s": after_s,
        "matched": sorted({t.w_text[i] for i in idx}),
        "found": int(idx.size),
        "skipped": int((~keep).sum()),
        "removed": [],
    }
    if not keep.any():
        raise ParameterError(
            f"keyword {w!r}: all {idx.size} occurrence(s) in {t.path} lie outside the motion of their "
            "recording (after its end, or before its start), so there is no gesture to keep"
        )
    return SubDatabase(
        word=w, start=start, length=length, recording=rec[keep].astype(np.int32), word_index=idx[keep],
        mask=_mask_of(start, length, t.n_frames) if with_mask else None, definition=definition,
    )


# --------------------------------------------------------------------------
# editing (atomic, through gesturedb.db.storage)
# --------------------------------------------------------------------------

def _open(db_path):
    return Database(db_path)


class KeywordAdded(NamedTuple):
    """One row of :func:`add_keywords`: what was written for a keyword (its mask is not kept in memory)."""

    word: str
    occurrences: int
    n_frames: int  # frames in the stretches, counting overlaps twice (as SubDatabase.n_frames)
    skipped: int  # occurrences outside the motion


def _keyword_names(words) -> list[str]:
    """Validated sub-database names of ``words`` in order, each once."""
    if isinstance(words, (str, bytes)) or not hasattr(words, "__iter__"):
        raise ParameterError(f"words: expected a list of words, got {type(words).__name__} {echo(words)}")
    names = list(dict.fromkeys(_keyword_name(w) for w in words))
    if not names:
        raise ParameterError("words: expected at least one word, got none")
    return names


def read_word_list(path) -> list[str]:
    """Keywords from a text file: one word per line; blank lines and ``#`` comments are skipped.

    Raises
    ------
    InputFileError
        The file cannot be read, or a line is not one word (the message names the line).
    """

    lines = read_text_lines(path)
    words = []
    for k, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        try:
            _keyword_name(text)
        except ParameterError as exc:
            raise InputFileError(path, f"line {k}: {exc}") from None
        words.append(text)
    if not words:
        raise InputFileError(path, "expected one keyword per line, got no word")
    return words


def _add(db_path, names: list[str], before_s: float, after_s: float, replace: bool, keep: bool):
    """Add the sub-databases of ``names`` in one locked edit; the written SubDatabases if ``keep``."""

    with storage.locked(db_path):
        # every check reads the file under the lock (nothing can change it before the write) and runs
        # before the copy, so a refused edit never copies the file
        with _open(db_path) as db:
            t = _tables(db)
            g = db.h5.get(schema.SUBDB_GROUP)
            existing = {} if g is None else {w: _read_subdb(g[w], w, t.n_frames, t.path) for w in names if w in g}
        if existing and not replace:
            if len(existing) == 1:
                (w, sub), = existing.items()
                raise ParameterError(
                    f"keyword {w!r}: {t.path} already has its sub-database ({len(sub)} occurrences, "
                    f"{sub.before_s:g} s before, {sub.after_s:g} s after); pass replace=True "
                    "(--replace) to rebuild it, or drop it first"
                )
            raise ParameterError(
                f"keywords {echo_list(list(existing), quote=True)}: {t.path} already has their sub-databases; pass "
                "replace=True (--replace) to rebuild them, or drop them first (nothing was added)"
            )
        index = _token_index(t) if len(names) > 1 else None
        if index is not None:
            unknown = [w for w in names if w not in index]
            if len(unknown) > 1:
                raise ParameterError(
                    f"keywords: {len(unknown)} of the {len(names)} words are not among the {len(t.w_text)} words of "
                    f"{t.path}: {echo_list(unknown, quote=True)} "
                    "(nothing was added)"
                )
        # stretches only (no masks) for all words first: every refusal comes before the copy
        plans = [_occurrences(t, w, before_s, after_s, index=index, with_mask=False) for w in names]
        written = []
        with storage.edit(db_path) as h5:
            for sub in plans:
                full = SubDatabase(word=sub.word, start=sub.start, length=sub.length, recording=sub.recording,
                                   word_index=sub.word_index, mask=_mask_of(sub.start, sub.length, t.n_frames),
                                   definition=sub.definition)
                _write_subdb(h5, full)
                written.append(full if keep else KeywordAdded(sub.word, len(sub), sub.n_frames,
                                                              int(sub.definition["skipped"])))
    return written


def add_keyword(db_path, word: str, *, before_s: float = 0.5, after_s: float = 1.0,
                replace: bool = False) -> SubDatabase:
    """Create the sub-database of a keyword in a database file (atomic edit).

    Parameters
    ----------
    db_path : path
        A gesture database; rewritten atomically (see :mod:`gesturedb.db.storage`).
    word : str
        The keyword; matched case-insensitively against whole words.
    before_s, after_s : float >= 0, seconds
        Context kept around each occurrence. The paper does not give one; a
        gesture's preparation and stroke usually start shortly before or with its
        word and the stroke and retraction run on after it, hence the defaults
        0.5 s before and 1.0 s after.
    replace : bool
        Rebuild an existing sub-database of the same word (its removed
        occurrences come back).

    Returns
    -------
    SubDatabase
        What was written.

    Raises
    ------
    ParameterError
        The word never occurs (with close words as suggestions), or its
        sub-database exists and ``replace`` is false.
    """
    w = _keyword_name(word)
    before_s = _check_seconds("before_s", before_s)
    after_s = _check_seconds("after_s", after_s)
    return _add(db_path, [w], before_s, after_s, replace, keep=True)[0]


def add_keywords(db_path, words, *, before_s: float = 0.5, after_s: float = 1.0,
                 replace: bool = False) -> list[KeywordAdded]:
    """Create the sub-databases of several keywords in one atomic edit (one copy of the file).

    Parameters
    ----------
    db_path : path
    words : iterable of str
        Keywords (repeats count once), e.g. :func:`read_word_list` of a file.
    before_s, after_s, replace
        As for :func:`add_keyword`, for every word.

    Returns
    -------
    list of KeywordAdded
        ``(word, occurrences, n_frames, skipped)`` per keyword, in order. The
        masks are written one keyword at a time and not kept, so memory does not
        grow with the number of words.

    Raises
    ------
    ParameterError
        A word never occurs, or (without ``replace``) already has a
        sub-database: the whole edit is refused and the file is unchanged.
    """
    names = _keyword_names(words)
    before_s = _check_seconds("before_s", before_s)
    after_s = _check_seconds("after_s", after_s)
    return _add(db_path, names, before_s, after_s, replace, keep=False)


def _indices(value, n: int, word: str, path: str) -> list[int]:
    items = [value] if isinstance(value, (int, np.integer, bool, np.bool_)) or not hasattr(value, "__iter__") else list(value)
    if not items:
        raise ParameterError(f"index: expected at least one occurrence of {word!r}, got none")
    for i in items:
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)) or not 0 <= i < n:
            raise ParameterError(
                f"index: expected an occurrence of {word!r} in [0, {n}) (see `gesturedb keywords {path} show "
                f"{word}`), got {echo(i)}"
            )
    return sorted({int(i) for i in items})


def remove_occurrence(db_path, word: str, index) -> SubDatabase:
    """Take occurrences (indices as listed by :func:`show`) out of a sub-database (atomic edit).

    ``index`` is one index or several, all numbered as before this edit (removing
    0 and 3 removes the occurrences :func:`show` lists as 0 and 3). The mask is
    recomputed from the remaining stretches and the occurrences' word indices are
    recorded in ``definition["removed"]``. Removing every occurrence is refused:
    drop the sub-database instead (an empty one would make every keyword step fail).

    The indices are read and checked under the database's write lock: two
    concurrent removals act as if run one after the other (the numbering of the
    second is that of the file the first left).

    Returns
    -------
    SubDatabase
        The sub-database after the removal.
    """

    with storage.locked(db_path):
        with _open(db_path) as db:
            sub = get_subdatabase(db, word)
            n_frames = db.n_frames
            path = db.path
        n = len(sub)
        drop = _indices(index, n, sub.word, path)
        if len(drop) == n:
            which = (f"occurrence {drop[0]} is the last one" if n == 1
                     else f"occurrences {echo_list(drop)} are all {n}")
            raise ParameterError(
                f"keyword {sub.word!r}: {which} of the sub-database in {path}; "
                "drop the sub-database instead (`drop WORD`)"
            )
        keep = np.ones(n, dtype=bool)
        keep[drop] = False
        definition = dict(sub.definition)
        definition["removed"] = list(definition.get("removed", [])) + [int(sub.word_index[i]) for i in drop]
        new = SubDatabase(
            word=sub.word, start=sub.start[keep], length=sub.length[keep], recording=sub.recording[keep],
            word_index=sub.word_index[keep], mask=_mask_of(sub.start[keep], sub.length[keep], n_frames),
            definition=definition,
        )
        with storage.edit(db_path) as h5:
            _write_subdb(h5, new)
    return new


def drop_keyword(db_path, word: str) -> SubDatabase:
    """Delete a whole sub-database (atomic edit); returns what was dropped."""

    with storage.locked(db_path):
        with _open(db_path) as db:
            sub = get_subdatabase(db, word)
        with storage.edit(db_path) as h5:
            store.delete(h5, f"{schema.SUBDB_GROUP}/{sub.word}")
            if not store.members(h5, schema.SUBDB_GROUP):
                store.delete(h5, schema.SUBDB_GROUP)
    return sub


# --------------------------------------------------------------------------
# looking
# --------------------------------------------------------------------------

class WordCount(NamedTuple):
    """One row of :func:`list_words`."""

    word: str
    count: int
    total_s: float  # summed duration of the spoken word, s


class Occurrence(NamedTuple):
    """One row of :func:`show`."""

    index: int
    recording: str
    time_s: float  # word start within its recording, s
    context: str  # the words around it, the keyword in [brackets]


def list_words(db, *, top: int | None = None) -> list[WordCount]:
    """The database's vocabulary, to choose keywords from.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    top : int or None
        Keep only the first ``top`` rows.

    Returns
    -------
    list of WordCount
        ``(word, count, total_s)`` sorted by count (most frequent first), then
        alphabetically; ``total_s`` is the summed spoken duration of the word (s).
        An entry holding several words (GENEA's ``"there is"``) counts for each of
        them, its duration shared equally.
    """
    if top is not None:
        top = _check_int("top", top, 1)
    w = db.words
    dur = np.asarray(w.end_s, dtype=np.float64) - np.asarray(w.start_s, dtype=np.float64)
    count: Counter = Counter()
    total: dict[str, float] = {}
    for text, d in zip(w.text, dur):
        toks = _tokens(text)
        for k in toks:
            count[k] += 1
            total[k] = total.get(k, 0.0) + float(d) / len(toks)
    rows = sorted((WordCount(k, c, round(total[k], 6)) for k, c in count.items()), key=lambda r: (-r.count, r.word))
    return rows[:top] if top is not None else rows


def _context(t: _Tables, wi: int, n_context: int) -> str:
    rec = t.w_rec[wi]
    lo = wi
    while lo > 0 and wi - lo < n_context and t.w_rec[lo - 1] == rec:
        lo -= 1
    hi = wi
    while hi + 1 < len(t.w_text) and hi - wi < n_context and t.w_rec[hi + 1] == rec:
        hi += 1
    parts = [t.w_text[i] if i != wi else f"[{t.w_text[i]}]" for i in range(lo, hi + 1)]
    return ("... " if lo > 0 and t.w_rec[lo - 1] == rec else "") + " ".join(parts) + (
        " ..." if hi + 1 < len(t.w_text) and t.w_rec[hi + 1] == rec else "")


def show(db, word: str, *, n_context: int = 3) -> list[Occurrence]:
    """The occurrences of a keyword with the words around them.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    word : str
        A keyword with a sub-database: its occurrences, numbered as
        :func:`remove_occurrence` takes them. Any other word: the occurrences
        :func:`add_keyword` would collect (raises if the word never occurs).
    n_context : int
        Words shown before and after (within the same recording).

    Returns
    -------
    list of Occurrence
        ``(index, recording, time_s, context)``.
    """
    n_context = _check_int("n_context", n_context, 0)
    w = _keyword_name(word)
    t = _tables(db)
    subs = subdatabases(db)
    if w in subs:
        word_index = subs[w].word_index
    else:
        word_index = _occurrences(t, w, 0.0, 0.0).word_index
    return [
        Occurrence(i, t.rec_names[int(t.w_rec[wi])], float(t.w_start[wi]), _context(t, int(wi), n_context))
        for i, wi in enumerate(word_index)
    ]



# --------------------------------------------------------------------------
# synthesis
# --------------------------------------------------------------------------

def _read_words(transcript):
    if isinstance(transcript, (str, os.PathLike)):
        transcript = read_transcript(transcript)
    missing = [a for a in ("start_s", "end_s", "text") if not hasattr(transcript, a)]
    if missing:
        raise ParameterError(
            f"transcript: expected a path or a Words object (start_s, end_s, text), got "
            f"{type(transcript).__name__} without {', '.join(missing)}"
        )
    start = np.asarray(transcript.start_s, dtype=np.float64).reshape(-1)
    end = np.asarray(transcript.end_s, dtype=np.float64).reshape(-1)
    text = [_tokens(x) for x in transcript.text]
    if not (start.shape[0] == end.shape[0] == len(text)):
        raise ParameterError(
            f"transcript: expected start_s, end_s and text of equal length, got {start.shape[0]}, "
            f"{end.shape[0]}, {len(text)}"
        )
    return start, end, text


def keyword_step_masks(
    db,
    transcript,
    *,
    n_steps: int,
    step: int,
    n_out_frames: int,
    only: Sequence[str] | None = None,
    compact: bool = False,
):
    """Per-step allowed bitsets from the keywords of the input speech.

    Parameters
    ----------
    db : gesturedb.db.database.Database
    transcript : path or Words
        Word timings of the input speech (TextGrid / GENEA TSV / JSON, read with
        :func:`gesturedb.io.read_transcript`), or an object with ``start_s``,
        ``end_s`` (seconds) and ``text``.
    n_steps : int
        Search steps, ``ceil(n_out_frames / step)``.
    step : int >= 1
        Frames per step; step ``i`` covers output frames
        ``[i * step, min((i + 1) * step, n_out_frames))``.
    n_out_frames : int >= 1
        Length of the output at the database fps.
    only : list of str or None
        Use only these keywords (each must have a sub-database).

    compact : bool
        Return ``bits`` as a :class:`gesturedb.control.StepBitsets` (each distinct
        row once) instead of the array.

    Returns
    -------
    (bits, labels) or None
        ``bits`` : ndarray [shape=(n_steps, B)], uint64, C-contiguous: a step whose
        frames overlap an occurrence of a keyword in the transcript (the word's
        interval in frames at ``db.fps``, see the module notes) gets that
        keyword's sub-database mask, every other step all frames.
        ``labels`` : list of str or None, the keyword of each step.
        When several keywords overlap one step, the one covering most of its
        frames wins; on a tie, the one whose covered frames start first, then the
        alphabetically first. None when no keyword of the database (of
        ``only``) is said inside the output.
    """

    step = _check_int("step", step, 1)
    n_out_frames = _check_int("n_out_frames", n_out_frames, 1)
    n_steps = _check_int("n_steps", n_steps, 1)
    want = -(-n_out_frames // step)
    if n_steps != want:
        raise ParameterError(
            f"n_steps: expected ceil(n_out_frames / step) = ceil({n_out_frames} / {step}) = {want}, got {n_steps}"
        )
    subs = subdatabases(db)
    if only is not None:
        if isinstance(only, str):
            only = [only]
        chosen = {}
        for w in only:
            k = _keyword_name(w)
            if k not in subs:
                raise ParameterError(_missing_message(k, list(subs), db.path))
            chosen[k] = subs[k]
        subs = chosen
    if not subs:
        return None

    start, end, text = _read_words(transcript)
    first, stop = time_to_frames(start, end, db.fps)
    first = np.clip(first, 0, n_out_frames)
    stop = np.clip(stop, 0, n_out_frames)
    coverage: dict[str, np.ndarray] = {}
    for a, b, toks in zip(first, stop, text):
        for w in toks:
            if w in subs and b > a:
                coverage.setdefault(w, np.zeros(n_steps * step, dtype=bool))[a:b] = True
    if not coverage:
        return None

    keys = sorted(coverage)
    cov = np.stack([coverage[k] for k in keys]).reshape(len(keys), n_steps, step)  # (K, n_steps, step)
    covered = cov.sum(axis=2)  # frames of each step covered by each keyword
    first_in_step = np.where(cov.any(axis=2), cov.argmax(axis=2), step)
    # lexsort: last key is primary -> most frames, then earliest frame, then keys order (alphabetical)
    order = np.lexsort((np.arange(len(keys))[:, None].repeat(n_steps, 1), first_in_step, -covered), axis=0)
    best = order[0]
    has = covered.max(axis=0) > 0

    # row 0: every frame, then one row per keyword
    rows = np.stack([control.full_mask(db.n_frames)] + [subs[k].mask for k in keys])
    of_step = np.where(has, best + 1, 0).astype(np.int64)
    labels: list[str | None] = [keys[int(best[i])] if has[i] else None for i in range(n_steps)]
    bits = control.StepBitsets(rows, of_step)
    return (bits if compact else np.ascontiguousarray(np.asarray(bits))), labels
