"""Issue 41: edits that race, edits through links, and edits that must not grow the file.

Every race runs ROUNDS times with real processes (fork), started together at a
barrier; each round is bounded by JOIN_S, so a hang fails the test instead of
stalling the suite.
"""
from __future__ import annotations

import multiprocessing
import os
import shutil

import h5py
import numpy as np
import pytest

import gesturedb
import gesturedb.control
from gesturedb.db import edit as dbedit
from gesturedb.db import keywords as kw
from gesturedb.db import storage
from gesturedb.errors import GestureDBError, InputFileError, ParameterError

ROUNDS = 10
JOIN_S = 60.0
CTX = multiprocessing.get_context("fork")


def _child(fn, args, kwargs, barrier, queue, slot):
    try:
        barrier.wait(JOIN_S)
        out = fn(*args, **kwargs)
        queue.put((slot, "ok", None if out is None else _summary(out)))
    except GestureDBError as exc:
        queue.put((slot, "refused", f"{type(exc).__name__}: {exc}"))
    except BaseException as exc:  # anything else is a bug: report it, never hang the parent
        queue.put((slot, "crashed", f"{type(exc).__name__}: {exc}"))


def _summary(out):
    return len(out) if hasattr(out, "__len__") else repr(out)


def race(*calls) -> list[tuple[str, object]]:
    """Run ``(fn, args, kwargs)`` calls in separate processes released together; their outcomes in order."""
    barrier = CTX.Barrier(len(calls))
    queue = CTX.Queue()
    procs = [CTX.Process(target=_child, args=(fn, args, kwargs, barrier, queue, i))
             for i, (fn, args, kwargs) in enumerate(calls)]
    for p in procs:
        p.start()
    try:
        got = dict((slot, (state, detail)) for slot, state, detail in (queue.get(timeout=JOIN_S) for _ in procs))
    finally:
        for p in procs:
            p.join(JOIN_S)
            if p.is_alive():
                p.kill()
                pytest.fail(f"an edit process hung for more than {JOIN_S:g} s")
    assert all(p.exitcode == 0 for p in procs), [p.exitcode for p in procs]
    out = [got[i] for i in range(len(calls))]
    assert not any(state == "crashed" for state, _ in out), out
    return out


@pytest.fixture()
def db_copy(scott_db_path, tmp_path):
    p = tmp_path / "db.h5"
    shutil.copyfile(scott_db_path, p)
    return p


def _like(path) -> kw.SubDatabase:
    with gesturedb.open(path) as db:
        return kw.get_subdatabase(db, "like")


# ---------------------------------------------------------------- case 1: concurrent removals

def test_concurrent_removals_are_both_applied_or_the_second_is_refused(scott_db_path, tmp_path):
    base = tmp_path / "base.h5"
    shutil.copyfile(scott_db_path, base)
    kw.add_keyword(base, "like")
    orig = _like(base)
    assert len(orig) == 4
    seen = set()
    for _ in range(ROUNDS):
        p = tmp_path / "k.h5"
        shutil.copyfile(base, p)
        (s0, d0), (s3, d3) = race((kw.remove_occurrence, (p, "like", 0), {}),
                                  (kw.remove_occurrence, (p, "like", 3), {}))
        after = _like(p)
        if s0 == s3 == "ok":  # 3 went first, then 0: both occurrences gone, nothing else
            np.testing.assert_array_equal(after.word_index, orig.word_index[[1, 2]])
            assert sorted(after.definition["removed"]) == sorted(int(orig.word_index[i]) for i in (0, 3))
        else:  # 0 went first: 3 no longer exists, exactly as when run one after the other
            assert (s0, s3) == ("ok", "refused"), (d0, d3)
            assert "ParameterError: index: expected an occurrence of 'like' in [0, 3)" in d3 and "got 3" in d3
            np.testing.assert_array_equal(after.word_index, orig.word_index[1:])
            assert after.definition["removed"] == [int(orig.word_index[0])]
        seen.add((s0, s3))
    # sequentially, the second is refused the same way
    p = tmp_path / "seq.h5"
    shutil.copyfile(base, p)
    kw.remove_occurrence(p, "like", 0)
    with pytest.raises(ParameterError, match=r"index: expected an occurrence of 'like' in \[0, 3\).*got 3"):
        kw.remove_occurrence(p, "like", 3)


def test_several_occurrences_go_in_one_removal_numbered_as_before_it(scott_db_path, tmp_path):
    p = tmp_path / "k.h5"
    shutil.copyfile(scott_db_path, p)
    kw.add_keyword(p, "like")
    orig = _like(p)
    new = kw.remove_occurrence(p, "like", [3, 0])
    np.testing.assert_array_equal(new.word_index, orig.word_index[[1, 2]])
    np.testing.assert_array_equal(_like(p).mask, new.mask)
    with pytest.raises(ParameterError, match=r"keyword 'like': occurrences 0, 1 are all 2 .*drop"):
        kw.remove_occurrence(p, "like", [0, 1])
    with pytest.raises(ParameterError, match=r"index: expected an occurrence of 'like' in \[0, 2\).*got 5"):
        kw.remove_occurrence(p, "like", [0, 5])
    with pytest.raises(ParameterError, match=r"index: expected at least one occurrence of 'like', got none"):
        kw.remove_occurrence(p, "like", [])


# ---------------------------------------------------------------- case 2: the same name twice at once

def test_concurrent_masks_add_of_one_name_refuses_the_second(db_copy, tmp_path):
    exprs = ("hand_speed < p30", "hand_speed > p70")
    for _ in range(ROUNDS):
        p = tmp_path / "m.h5"
        shutil.copyfile(db_copy, p)
        out = race(*[(dbedit.save_mask, (p, "same", e), {}) for e in exprs])
        states = sorted(s for s, _ in out)
        assert states == ["ok", "refused"], out
        winner = exprs[[s for s, _ in out].index("ok")]
        refused = out[[s for s, _ in out].index("refused")][1]
        assert f"mask 'same' already exists in {p} (definition {winner!r}); pass replace=True" in refused
        with gesturedb.open(p) as db:
            assert db.mask_definitions["same"] == winner
    with pytest.raises(ParameterError, match=r"mask 'same' already exists in .*m\.h5"):
        dbedit.save_mask(p, "same", exprs[0])


def test_concurrent_keywords_add_of_one_word_refuses_the_second(db_copy, tmp_path):
    for _ in range(ROUNDS):
        p = tmp_path / "k.h5"
        shutil.copyfile(db_copy, p)
        out = race((kw.add_keyword, (p, "like"), {"after_s": 1.0}),
                   (kw.add_keyword, (p, "like"), {"after_s": 2.0}))
        assert sorted(s for s, _ in out) == ["ok", "refused"], out
        won = [1.0, 2.0][[s for s, _ in out].index("ok")]
        refused = out[[s for s, _ in out].index("refused")][1]
        assert f"keyword 'like': {p} already has its sub-database (4 occurrences, 0.5 s before, {won:g} s after)" \
            in refused
        assert _like(p).after_s == won


def test_concurrent_edits_of_different_things_all_survive(db_copy, tmp_path):
    for _ in range(ROUNDS):
        p = tmp_path / "e.h5"
        shutil.copyfile(db_copy, p)
        out = race((dbedit.save_mask, (p, "calm", "hand_speed < p30"), {}),
                   (kw.add_keyword, (p, "like"), {}),
                   (dbedit.save_masks, (p, {"busy": "hand_speed > p70", "both": "busy or calm_not"}), {}),
                   )
        # the third refers to a mask that does not exist: refused, the others applied
        assert [s for s, _ in out] == ["ok", "ok", "refused"], out
        assert "calm_not" in out[2][1]
        with gesturedb.open(p) as db:
            assert "calm" in db.masks and "busy" not in db.masks and "like" in kw.subdatabases(db)


# ---------------------------------------------------------------- case 5: symbolic links

def test_edits_through_a_symlink_change_the_real_file_and_keep_the_link(db_copy, tmp_path):
    from gesturedb.cli.main import main

    real = db_copy
    link = tmp_path / "link.h5"
    os.symlink(real, link)
    assert main(["masks", str(link), "add", "calm", "hand_speed < p30"]) == 0
    assert main(["keywords", str(link), "add", "like"]) == 0
    assert os.path.islink(link) and os.readlink(link) == str(real)
    with gesturedb.open(real) as db:
        assert db.mask_definitions["calm"] == "hand_speed < p30" and "like" in kw.subdatabases(db)
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".tmp")]
    # the lock is the real file's: an edit through the link and one of the file serialise
    assert storage.lock_path(link) == storage.lock_path(real)
    for i in range(ROUNDS):
        out = race((dbedit.save_mask, (link, f"a{i}", "hand_speed < p40"), {}),
                   (dbedit.save_mask, (real, f"b{i}", "hand_speed > p60"), {}))
        assert [s for s, _ in out] == ["ok", "ok"], out
    assert os.path.islink(link)
    with gesturedb.open(real) as db:
        assert {f"a{i}" for i in range(ROUNDS)} | {f"b{i}" for i in range(ROUNDS)} <= set(db.masks)


def test_a_relative_symlink_in_another_folder_is_followed(db_copy, tmp_path):
    other = tmp_path / "elsewhere"
    other.mkdir()
    link = other / "db.h5"
    os.symlink(os.path.relpath(db_copy, other), link)
    dbedit.save_mask(link, "calm", "hand_speed < p30")
    assert os.path.islink(link)
    with gesturedb.open(db_copy) as db:
        assert "calm" in db.masks
    assert not [f for f in os.listdir(other) if not f == "db.h5"]  # no lock or temporary beside the link


def test_a_dangling_symlink_is_a_one_line_error(tmp_path):
    link = tmp_path / "gone.h5"
    os.symlink(tmp_path / "missing.h5", link)
    with pytest.raises(InputFileError, match=r"gone\.h5: no such file"):
        dbedit.save_mask(link, "calm", "hand_speed < p30")


# ---------------------------------------------------------------- case 18: space and batches

def test_repeated_edits_do_not_grow_the_file(db_copy):
    kw.add_keyword(db_copy, "like")
    dbedit.save_mask(db_copy, "calm", "hand_speed < p30")
    sizes = []
    for i in range(6):
        kw.add_keyword(db_copy, "like", after_s=1.0 + 0.1 * (i % 2), replace=True)
        dbedit.save_mask(db_copy, "calm", f"hand_speed < p{30 + i % 2}", replace=True)
        sizes.append(os.path.getsize(db_copy))
    # the same content every other round: the same size (a byte copy grew ~4 kB per replace)
    assert sizes[2] == sizes[4] and sizes[3] == sizes[5], sizes
    with h5py.File(db_copy, "r") as h5:
        assert int(h5.id.get_filesize()) == sizes[-1]


def test_many_keywords_in_one_edit_equal_one_at_a_time(db_copy, tmp_path):
    words = ["like", "time", "the", "and", "you", "i"]
    one = tmp_path / "one.h5"
    shutil.copyfile(db_copy, one)
    for w in words:
        kw.add_keyword(one, w)
    added = kw.add_keywords(db_copy, words + ["LIKE"])  # a repeat counts once
    assert [a.word for a in added] == words
    with gesturedb.open(one) as a, gesturedb.open(db_copy) as b:
        sa, sb = kw.subdatabases(a), kw.subdatabases(b)
    assert list(sa) == list(sb) == sorted(words)
    for w in words:
        for f in ("start", "length", "recording", "word_index", "mask"):
            np.testing.assert_array_equal(getattr(sa[w], f), getattr(sb[w], f))
        assert sa[w].definition == sb[w].definition
        got = next(x for x in added if x.word == w)
        assert (got.occurrences, got.n_frames) == (len(sb[w]), sb[w].n_frames)


def test_a_batch_is_refused_whole(db_copy):
    before = open(db_copy, "rb").read()
    with pytest.raises(ParameterError, match=r"keywords: 2 of the 3 words are not among the \d+ words of .*db\.h5: "
                                             r"'zzyzx', 'qwxq' \(nothing was added\)"):
        kw.add_keywords(db_copy, ["like", "zzyzx", "qwxq"])
    with pytest.raises(ParameterError, match=r"keyword 'zzyzx': not among the \d+ words of .*db\.h5"):
        kw.add_keywords(db_copy, ["like", "zzyzx"])
    kw.add_keywords(db_copy, ["like", "time"])
    mid = open(db_copy, "rb").read()
    with pytest.raises(ParameterError, match=r"keywords 'time', 'like': .*db\.h5 already has their sub-databases"):
        kw.add_keywords(db_copy, ["time", "like", "you"])
    with pytest.raises(ParameterError, match=r"keyword: expected a single word .*got 'two words'"):
        kw.add_keywords(db_copy, ["you", "two words"])
    with pytest.raises(ParameterError, match=r"words: expected a list of words, got str 'you'"):
        kw.add_keywords(db_copy, "you")
    with pytest.raises(ParameterError, match=r"words: expected at least one word, got none"):
        kw.add_keywords(db_copy, [])
    assert open(db_copy, "rb").read() == mid != before
    with pytest.raises(ParameterError, match=r"mask 'b': given twice in one edit"):
        dbedit.save_masks(db_copy, [("b", "hand_speed < p30"), ("b", "hand_speed < p40")])
    with pytest.raises(ParameterError, match=r"mask 'none' = 'hand_speed < -1' allows no frame of .*db\.h5"):
        dbedit.save_masks(db_copy, {"ok": "hand_speed < p30", "none": "hand_speed < -1"})
    with pytest.raises(ParameterError, match=r"mask name: expected a name matching .*got 'a/b'"):
        dbedit.save_masks(db_copy, {"ok": "hand_speed < p30", "a/b": "hand_speed < p40"})
    assert open(db_copy, "rb").read() == mid


def test_masks_of_one_edit_may_name_the_ones_before_them(db_copy):
    res = dbedit.save_masks(db_copy, {"slow": "hand_speed < p40", "slow_and_near": "slow and hand_distance < p50"})
    with gesturedb.open(db_copy) as db:
        ref = gesturedb.control.compile_mask("hand_speed < p40 and hand_distance < p50", controls=db.controls,
                                             n_frames=db.n_frames)
        np.testing.assert_array_equal(db.masks["slow_and_near"], ref.words)
        assert db.mask_definitions["slow_and_near"] == "slow and hand_distance < p50"
    assert list(res) == ["slow", "slow_and_near"]


def test_cli_adds_many_keywords_and_masks_in_one_edit(db_copy, tmp_path, capsys):
    from gesturedb.cli.main import main

    words = tmp_path / "words.txt"
    words.write_text("# keywords\nlike\n\ntime  # the common one\n")
    assert main(["keywords", str(db_copy), "add", "you", "--from", str(words)]) == 0
    out = capsys.readouterr().out
    assert [ln.split(":")[1].split(",")[0].strip() for ln in out.splitlines()] == ["'you'", "'like'", "'time'"]
    masks = tmp_path / "masks.txt"
    masks.write_text("calm = hand_speed < p30\n# a comment\nbusy=hand_speed >= p70  # fast\n")
    assert main(["masks", str(db_copy), "add", "near", "hand_distance < p50", "--from", str(masks)]) == 0
    out = capsys.readouterr().out
    assert [ln.split(":")[0] for ln in out.splitlines()] == ["saved near", "saved calm", "saved busy"]
    with gesturedb.open(db_copy) as db:
        assert db.mask_definitions["busy"] == "hand_speed >= p70"
        assert set(kw.subdatabases(db)) == {"you", "like", "time"}
        like = kw.subdatabases(db)["like"]
    assert main(["keywords", str(db_copy), "remove", "like", "3", "0"]) == 0
    assert capsys.readouterr().out.strip() == f"removed occurrence 0, 3 of 'like' from {db_copy}; 2 left"
    np.testing.assert_array_equal(_like(db_copy).word_index, like.word_index[[1, 2]])

    def one_line(argv, *needles):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err, err
        for n in needles:
            assert n in err, (n, err)

    bad = tmp_path / "bad.txt"
    bad.write_text("like\ntwo words\n")
    one_line(["keywords", str(db_copy), "add", "--from", str(bad)],
             f"{bad}: line 2: keyword: expected a single word")
    one_line(["keywords", str(db_copy), "add"], "add: expected at least one WORD or --from FILE")
    bad.write_text("calm = hand_speed < p30\nhand_speed > p20\n")
    one_line(["masks", str(db_copy), "add", "--from", str(bad)], f"{bad}: line 2: expected NAME = EXPRESSION")
    bad.write_text("9lives = hand_speed < p30\n")
    one_line(["masks", str(db_copy), "add", "--from", str(bad)], f"{bad}: line 1: mask name: expected a name")
    one_line(["masks", str(db_copy), "add", "x", "hand_speed < p30", "y"], "add: expected NAME EXPR pairs, got 3")
    one_line(["masks", str(db_copy), "add", "--from", str(tmp_path / "nope.txt")], "nope.txt: cannot read as text")


# ---------------------------------------------------------------- the lock itself

def _try_lock(path, queue):
    try:
        with storage.locked(path, timeout_s=0.5):
            queue.put("got it")
    except InputFileError as exc:
        queue.put(str(exc))


def test_the_lock_is_reentrant_in_a_thread_but_not_inherited_by_a_forked_child(db_copy):
    with storage.locked(db_copy):
        with storage.locked(db_copy):  # an edit inside an edit's checks shares the hold
            queue = CTX.Queue()
            child = CTX.Process(target=_try_lock, args=(db_copy, queue))
            child.start()
            got = queue.get(timeout=JOIN_S)
            child.join(JOIN_S)
        assert "another gesturedb process is writing this database" in got, got
    child = CTX.Process(target=_try_lock, args=(db_copy, queue))
    child.start()
    assert queue.get(timeout=JOIN_S) == "got it"
    child.join(JOIN_S)


def test_a_huge_word_in_a_word_list_is_a_short_line(db_copy, tmp_path):
    words = tmp_path / "words.txt"
    words.write_text("like\n" + "x" * 200_000 + " y\n")
    with pytest.raises(InputFileError) as err:
        kw.read_word_list(words)
    msg = str(err.value)
    assert msg.startswith(f"{words}: line 2: keyword: expected a single word") and len(msg) < 600, msg[:700]
    with pytest.raises(ParameterError, match=r"keywords: 2 of the 3 words .*'zz+'\.\.\. \(100000 characters\)"):
        kw.add_keywords(db_copy, ["like", "z" * 100_000, "qq" * 50_000])


def test_the_lock_file_exists_only_while_a_writer_holds_it(tmp_path):
    """No ``.NAME.lock`` is left beside a database, and a writer waiting for the lock gets it when
    the holder removes the file on release (it then locks the new file, not the removed one)."""
    import threading
    import time

    db = tmp_path / "db.h5"
    lp = storage.lock_path(db)
    held, release, seen = threading.Event(), threading.Event(), []

    def holder():
        with storage.locked(db):
            held.set()
            release.wait(30)

    def waiter():
        with storage.locked(db, timeout_s=30):
            seen.append(os.path.exists(lp))

    a = threading.Thread(target=holder)
    a.start()
    assert held.wait(30) and os.path.exists(lp)
    b = threading.Thread(target=waiter)
    b.start()
    time.sleep(0.3)
    assert seen == []  # a second writer waits (another thread holds the lock through its own descriptor)
    release.set()
    a.join(30)
    b.join(30)
    assert seen == [True] and os.listdir(tmp_path) == []
