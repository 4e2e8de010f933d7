"""The k-NN synthesis' repetition guard and the repeat statistics (gesturedb/synth/repeats.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gesturedb import search
from gesturedb.control import full_mask, unpack_bits
from gesturedb.errors import ParameterError, SearchError
from gesturedb.synth import Searcher
from gesturedb.synth.repeats import (
    Overlaps,
    clear_frames,
    guarded_search,
    repeat_of,
    repeat_stats,
    windows_of,
)
from test_search import continuous_db, oracle_step, pack_bits

INPUT = "inputs/2_scott_0_2_2.wav"


def test_clear_frames_matches_a_bool_reference():
    rng = np.random.default_rng(3)
    for F in (1, 63, 64, 65, 200, 1000):
        base = rng.random(F) < 0.7
        ranges = [tuple(sorted(rng.integers(0, F + 5, size=2))) for _ in range(rng.integers(0, 6))]
        want = base.copy()
        for a, b in ranges:
            want[a:b] = False
        got = clear_frames(pack_bits(base), ranges)
        np.testing.assert_array_equal(unpack_bits(got, F), want)


def test_overlaps_one_window_at_a_time_are_repeat_of():
    """What a live stream keeps per window (Overlaps, its array grown past 64 rows) gives repeat_of's answer."""
    rng = np.random.default_rng(4)
    frames, lengths = rng.integers(0, 400, size=300), rng.integers(1, 12, size=300)
    ov = Overlaps()
    assert [ov.add(f, n) for f, n in zip(frames, lengths)] == repeat_of(frames, lengths)
    assert ov.n == 300 and any(r is not None for r in repeat_of(frames, lengths))


def test_repeat_statistics_by_hand():
    # windows (first frame, length) in output order: 0 and 3 overlap 10..17; 2 continues 1; 4 overlaps 0 and 3
    frames = [10, 50, 58, 12, 16]
    lengths = [8, 8, 8, 8, 8]
    assert repeat_of(frames, lengths) == [None, None, None, 0, 3]
    st = repeat_stats(frames, lengths, out_frames=[0, 8, 16, 24, 32], fps=8.0)
    assert st == {"steps": 5, "repeats": 2, "distinct": 3, "max_plays": 3, "min_gap_s": 1.0}
    assert repeat_stats([], [])["max_plays"] == 0
    f, n, t = windows_of(np.array([10, 11, 12, 50, 51, 7]), np.array([3, 5]))
    assert f.tolist() == [10, 50, 7] and n.tolist() == [3, 2, 1] and t.tolist() == [0, 3, 5]


def _kernel_step(P, A, st, ln, step):
    def run(q, prev, allowed):
        return search.rank_sum_search(P, A, st, ln, q, prev, step=step, allowed=allowed)
    return run


def _no_candidate(i, t, n, row):
    return SearchError(f"step {i}")


def test_guard_zero_frames_is_the_kernel_search_and_the_guard_follows_the_spec():
    rng = np.random.default_rng(5)
    P, A, st, ln = continuous_db(rng, Dp=24, Da=14, n_segments=12, seg=48)
    F = P.shape[0]
    query = rng.standard_normal((200, A.shape[1])).astype(np.float32)
    init = P[7]
    full = full_mask(F)
    # one step at a time with no window recent enough to guard: the kernel's own loop
    d = guarded_search(_kernel_step(P, A, st, ln, 8), query=query, init_pose=init, step=8, allowed=None,
                       pose_row=P.__getitem__, full=full, guard_frames=0, no_candidate=_no_candidate)
    whole = search.rank_sum_search(P, A, st, ln, query, init, step=8)
    for f in ("segments", "starts", "frames", "lengths", "out_frames", "pose_rank", "audio_rank", "n_candidates"):
        np.testing.assert_array_equal(d[f], getattr(whole, f), err_msg=f)
    np.testing.assert_array_equal(d["pose_dist"], whole.pose_dist)
    # with a guard of 40 frames: each step is the spec's choice among the windows that do not
    # overlap one placed within the last 40 output frames
    g = guarded_search(_kernel_step(P, A, st, ln, 8), query=query, init_pose=init, step=8, allowed=None,
                       pose_row=P.__getitem__, full=full, guard_frames=40, no_candidate=_no_candidate)
    assert not g["relaxed"].any()
    prev = init
    changed = 0
    for i in range(len(g["frames"])):
        t = i * 8
        n = min(8, 200 - t)
        recent = [(g["frames"][j], g["frames"][j] + g["lengths"][j]) for j in range(i) if t - g["out_frames"][j] < 40]
        allowed = pack_bits(np.ones(F, bool))
        bits = unpack_bits(allowed, F)
        for a, b in recent:
            bits[a:b] = False
        want, _ = oracle_step(P, A, st, ln, prev, query[t:t + n], allowed=pack_bits(bits))
        assert (g["segments"][i], g["starts"][i]) == (want["segment"], want["start"])
        for a, b in recent:  # no overlap with a recent window
            assert not (g["frames"][i] < b and g["frames"][i] + n > a)
        changed += int(g["frames"][i] != d["frames"][i])
        prev = P[g["frames"][i] + n - 1]
    assert changed > 0  # the unguarded search did repeat itself here
    assert repeat_stats(g["frames"], g["lengths"], out_frames=g["out_frames"], fps=1.0)["min_gap_s"] >= 40


def test_guard_steps_aside_when_it_would_empty_a_step():
    rng = np.random.default_rng(9)
    P, A, st, ln = continuous_db(rng, Dp=24, Da=14, n_segments=6, seg=48)
    F = P.shape[0]
    query = rng.standard_normal((40, A.shape[1])).astype(np.float32)
    bits = np.zeros(F, bool)
    bits[st[2] + 5: st[2] + 15] = True  # three windows of 8 frames, all overlapping each other
    allowed = np.tile(pack_bits(bits), (5, 1))
    g = guarded_search(_kernel_step(P, A, st, ln, 8), query=query, init_pose=P[0], step=8, allowed=allowed,
                       pose_row=P.__getitem__, full=full_mask(F), guard_frames=100, no_candidate=_no_candidate)
    assert g["relaxed"].tolist() == [False, True, True, True, True]
    assert all(st[2] + 5 <= f <= st[2] + 7 for f in g["frames"])
    empty = allowed.copy()
    empty[3] = 0
    with pytest.raises(SearchError, match="step 3"):
        guarded_search(_kernel_step(P, A, st, ln, 8), query=query, init_pose=P[0], step=8, allowed=empty,
                       pose_row=P.__getitem__, full=full_mask(F), guard_frames=100, no_candidate=_no_candidate)


@pytest.mark.slow
def test_guard_on_the_real_database(scott_db, scott_dir):
    s = Searcher(scott_db)
    wav = scott_dir / INPUT
    off = s.synthesize(wav, repeat_guard_s=0)
    # the default: on, and no window is played again within 4 s of output
    on = s.synthesize(wav)
    assert on.options["repeat_guard_s"] == 4.0 and on.repeats["guard_s"] == 4.0
    assert on.repeats["min_gap_s"] >= 4.0 > off.repeats["min_gap_s"]
    # (not how often the most played window plays: the guard moves repeats apart, and on a one-minute
    # database that count follows the path it takes: 9 with the guard and 7 without on this input, 9
    # and 12 on 2_scott_0_4_4)
    # the same whole search, one kernel call per step with nothing to guard
    tiny = s.synthesize(wav, repeat_guard_s=0.01)
    np.testing.assert_array_equal(tiny.source_frames, off.source_frames)
    # the provenance agrees with the statistics, and the stream's overlap per step (from the windows it keeps
    # as an array, grown past its first 64 rows here) with repeat_of over the whole synthesis
    rep = [st["repeat_of"] for st in on.steps]
    assert len(rep) > 64
    assert rep == repeat_of([st["db_frame"] for st in on.steps], [st["out_end"] - st["out_start"] for st in on.steps])
    assert sum(r is not None for r in rep) == on.repeats["repeats"]
    for i, j in enumerate(rep):
        if j is not None:
            a, b = on.steps[i], on.steps[j]
            assert a["db_frame"] < b["db_frame"] + (b["out_end"] - b["out_start"])
            assert b["db_frame"] < a["db_frame"] + (a["out_end"] - a["out_start"])
            assert a["time_s"] - b["time_s"] >= 4.0 or a["guard_relaxed"]
    f, n, t = windows_of(on.source_frames, on.boundaries)
    assert repeat_stats(f, n, out_frames=t, fps=on.fps) == {k: on.repeats[k] for k in
                                                             ("steps", "repeats", "distinct", "max_plays", "min_gap_s")}
    with pytest.raises(ParameterError, match="repeat_guard_s: expected a number of seconds >= 0"):
        s.synthesize(wav, repeat_guard_s=-1)


@pytest.mark.slow
def test_guard_spreads_a_narrow_control(scott_db, scott_dir):
    s = Searcher(scott_db)
    wav = scott_dir / INPUT
    ctl = "left_wrist_speed > p85"
    off = s.synthesize(wav, control=ctl, repeat_guard_s=0)
    on = s.synthesize(wav, control=ctl, repeat_guard_s=8)
    # few windows pass this control, so they come back, but not within 8 s and less often
    assert off.repeats["min_gap_s"] < 8 <= on.repeats["min_gap_s"] or on.repeats["guard_relaxed"]
    assert on.repeats["max_plays"] < off.repeats["max_plays"]
    assert on.repeats["distinct"] >= off.repeats["distinct"]
    assert all(st["control"] == ctl for st in on.steps)


@pytest.mark.slow
def test_sharded_search_guards_the_same(scott_db, scott_dir, dask_client):
    wav = scott_dir / INPUT
    import soundfile as sf

    y, sr = sf.read(wav, dtype="float32")
    y = y[: 12 * sr]  # 12 s keep the per-step round trips short
    a = Searcher(scott_db).synthesize(y, sr=sr)
    b = Searcher(scott_db, client=dask_client, parts=2).synthesize(y, sr=sr)
    np.testing.assert_array_equal(a.source_frames, b.source_frames)
    assert a.repeats == b.repeats


@pytest.mark.slow
def test_cli_reports_repeats(scott_db_path, scott_dir, tmp_path, capsys):
    from gesturedb.cli.main import main

    out = tmp_path / "o.bvh"
    assert main(["synth", str(scott_db_path), "--audio", str(scott_dir / INPUT), "-o", str(out),
                 "--repeat-guard", "6"]) == 0
    line = capsys.readouterr().out
    prov = json.loads((tmp_path / "o.provenance.json").read_text())
    r = prov["repeats"]
    assert r["guard_s"] == 6.0 and prov["options"]["repeat_guard_s"] == 6.0
    assert f"{r['distinct']} distinct windows, {r['repeats']} repeats" in line
    assert all("repeat_of" in s and "guard_relaxed" in s for s in prov["steps"])
    assert main(["synth", str(scott_db_path), "--audio", str(scott_dir / INPUT), "-o", str(out),
                 "--method", "graph", "--repeat-guard", "6"]) == 2
    assert "--repeat-guard" in capsys.readouterr().err


@pytest.mark.slow
def test_eval_motion_counts_repeats(scott_db, scott_dir):
    from gesturedb.eval.evaluate import evaluate_inputs

    wav = scott_dir / "inputs/2_scott_0_3_3.wav"
    ev = evaluate_inputs(scott_db, [wav], systems=["random", "ranksum_pose"])
    rows = ev.inputs[0].metrics
    # from the evaluation's frame maps, the same numbers as the synthesis' own provenance
    res = Searcher(scott_db).synthesize(wav)
    assert (rows["ranksum_pose"]["repeats"], rows["ranksum_pose"]["max_plays"]) == \
        (res.repeats["repeats"], res.repeats["max_plays"])
    assert rows["random"]["max_plays"] >= 1
    text = ev.to_text()
    assert "repeats" in text and "max plays" in text
