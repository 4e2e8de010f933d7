"""Evaluation: baselines against brute force, Table 2 on the real recording, the held-out metrics report."""
from __future__ import annotations

import json

import numpy as np
import pytest

import gesturedb
from gesturedb.errors import ParameterError, SearchError
from gesturedb.eval import baselines as B
from gesturedb.eval import evaluate as E


@pytest.fixture(scope="module")
def mirror_db_path(scott_dir, tmp_path_factory):
    """The real recording with its mirrored copy: 1906 frames at 15 fps."""
    out = tmp_path_factory.mktemp("evaldb") / "scott_mirror.h5"
    gesturedb.build([scott_dir], out, mirror=True).close()
    return out


@pytest.fixture()
def mdb(mirror_db_path):
    with gesturedb.open(mirror_db_path) as db:
        yield db


@pytest.fixture(scope="module")
def speech(scott_dir):
    """Held-out speech of the same speaker (no motion), at the analysis rate."""
    from gesturedb.io import read_audio

    return read_audio(scott_dir / "inputs" / "2_scott_0_2_2.wav", sr=16000)


@pytest.fixture(scope="module")
def holdout(scott_dir):
    return E.evaluate_holdout(scott_dir, 48.0, 63.5, mirror=True)


# ------------------------------------------------------------------ candidate windows
def _brute_candidates(seg_start, seg_len, n, exclude=None):
    out = []
    for m, (s0, L) in enumerate(zip(seg_start, seg_len)):
        if exclude is not None and exclude[m]:
            continue
        out += [s0 + s for s in range(1, L - n + 1)]
    return np.array(out, dtype=np.int64)


def test_candidate_windows_follow_the_search_spec():
    seg_start = np.array([0, 10, 13, 40, 41], dtype=np.int64)
    seg_len = np.array([10, 3, 20, 1, 9], dtype=np.int64)
    excl = np.array([False, False, True, False, False])
    for n in (1, 2, 3, 8, 9, 30):
        for ex in (None, excl):
            got = B.candidate_windows(seg_start, seg_len, n, exclude=ex)
            np.testing.assert_array_equal(got, _brute_candidates(seg_start, seg_len, n, ex))
    with pytest.raises(ParameterError, match="exclude: expected bool"):
        B.candidate_windows(seg_start, seg_len, 2, exclude=np.zeros(2, bool))
    with pytest.raises(ParameterError, match="n: expected an integer >= 1"):
        B.candidate_windows(seg_start, seg_len, 0)


def test_step_layout_covers_every_output_frame_once():
    t, n = B.step_layout(100, 8)
    assert t.tolist() == list(range(0, 100, 8)) and n[-1] == 4 and n[:-1].tolist() == [8] * 12
    cover = np.zeros(100, int)
    for a, k in zip(t, n):
        cover[a:a + k] += 1
    assert (cover == 1).all()


# ------------------------------------------------------------------ baselines
def _query(mdb, speech):
    from gesturedb.synth import Searcher

    s = Searcher(mdb)
    return s, s.query_features(*speech)


def test_pose_only_picks_the_nearest_entry_pose_like_brute_force(mdb, speech):
    s, q = _query(mdb, speech)
    T = 204  # 25 full steps and a last one of 4 frames
    init = s.initial_pose("mean")
    ch = B.pose_only_windows(mdb.pose_features, s.seg_start, s.seg_len, init, n_frames=T, step=8)
    P = np.asarray(mdb.pose_features, dtype=np.float64)
    prev = init.astype(np.float64)
    for i, (t, n) in enumerate(zip(*B.step_layout(T, 8))):
        best, best_g = np.inf, None
        for _m, (s0, L) in enumerate(zip(s.seg_start, s.seg_len)):
            for off in range(1, L - n + 1):
                g = s0 + off
                d = float(((P[g - 1] - prev) ** 2).sum())
                if d < best:
                    best, best_g = d, g
        assert ch.frames[i] == best_g, f"step {i}"
        assert ch.distance[i] == pytest.approx(best, rel=1e-9, abs=1e-12)
        assert ch.out_frames[i] == t and ch.lengths[i] == n
        prev = P[best_g + n - 1]
    # it plays the database back: most steps continue the previous window at distance 0
    cont = ch.frames[1:] == ch.frames[:-1] + 8
    assert cont.mean() > 0.5 and np.all(ch.distance[1:][cont] == 0)


def test_random_windows_are_seeded_and_valid(mdb):
    from gesturedb.synth import Searcher

    s = Searcher(mdb)
    a = B.random_windows(s.seg_start, s.seg_len, n_frames=301, step=8, seed=7)
    b = B.random_windows(s.seg_start, s.seg_len, n_frames=301, step=8, seed=7)
    c = B.random_windows(s.seg_start, s.seg_len, n_frames=301, step=8, seed=8)
    np.testing.assert_array_equal(a.frames, b.frames)
    assert not np.array_equal(a.frames, c.frames)
    for g, n in zip(a.frames, a.lengths):
        assert g in set(_brute_candidates(s.seg_start, s.seg_len, int(n)).tolist())
    src = a.source_frames
    assert src.shape == (301,)
    for t, n, g in zip(a.out_frames, a.lengths, a.frames):
        np.testing.assert_array_equal(src[t:t + n], np.arange(g, g + n))
    np.testing.assert_array_equal(a.boundaries, a.out_frames[1:])
    # excluding every segment of the original leaves only mirrored windows
    ex = s.exclude_recordings(None)
    assert ex is None
    rec = np.asarray(s.seg_recording)
    only_mirror = B.random_windows(s.seg_start, s.seg_len, n_frames=301, step=8, seed=7, exclude=rec == 0)
    assert (mdb.frame_recording[only_mirror.source_frames] == 1).all()
    with pytest.raises(SearchError, match="no database window"):
        B.random_windows(s.seg_start, s.seg_len, n_frames=20, step=8, exclude=np.ones(len(rec), bool))


def _cosine_dist(Q, A, t, g, n):
    q = Q[t:t + n].astype(np.float64).ravel()
    a = A[g:g + n].astype(np.float64).ravel()
    den = np.linalg.norm(q) * np.linalg.norm(a)
    return 1.0 if den == 0 else 1.0 - float(q @ a) / den


def test_audio_only_matches_brute_force_and_beats_random(mdb, speech):
    s, q = _query(mdb, speech)
    A = np.asarray(mdb.audio_features)
    ch = B.audio_only_windows(A, s.seg_start, s.seg_len, q, step=8)
    T = q.shape[0]
    assert ch.n_frames == T and ch.source_frames.shape == (T,)
    t_all, n_all = B.step_layout(T, 8)
    cands = {int(n): _brute_candidates(s.seg_start, s.seg_len, int(n)) for n in np.unique(n_all)}
    # independent path: flatten the windows explicitly, every candidate, a third of the steps
    for i in range(0, len(t_all), 3):
        t, n = int(t_all[i]), int(n_all[i])
        d = np.array([_cosine_dist(q, A, t, g, n) for g in cands[n]])
        # the mirrored copy has the same audio: exact ties go to the earlier candidate
        first = int(np.flatnonzero(d <= d.min() + B.TIE_TOLERANCE)[0])
        assert ch.frames[i] == cands[n][first], f"step {i}"
        assert ch.distance[i] == pytest.approx(d.min(), abs=1e-9)
    rnd = B.random_windows(s.seg_start, s.seg_len, n_frames=T, step=8, seed=0)
    d_audio = np.mean([_cosine_dist(q, A, t, g, n) for t, g, n in zip(ch.out_frames, ch.frames, ch.lengths)])
    d_rand = np.mean([_cosine_dist(q, A, t, g, n) for t, g, n in zip(rnd.out_frames, rnd.frames, rnd.lengths)])
    assert d_audio < d_rand - 0.2, (d_audio, d_rand)


def test_baseline_bad_inputs(mdb):
    from gesturedb.synth import Searcher

    s = Searcher(mdb)
    with pytest.raises(ParameterError, match=r"init_pose: expected shape"):
        B.pose_only_windows(mdb.pose_features, s.seg_start, s.seg_len, np.zeros(3), n_frames=16)
    with pytest.raises(ParameterError, match=r"query: expected \(T, 14\)"):
        B.audio_only_windows(mdb.audio_features, s.seg_start, s.seg_len, np.zeros((10, 3)))
    with pytest.raises(ParameterError, match="step: expected an integer >= 1"):
        B.random_windows(s.seg_start, s.seg_len, n_frames=16, step=0)


# ------------------------------------------------------------------ helpers
def test_upper_body_joints_drop_the_legs_and_root(mdb):
    fj = E.feature_joint_indices(mdb)
    j = E.upper_body_joints(mdb.skeleton.parents, root=fj["root"], hips=[fj["left_hip"], fj["right_hip"]])
    names = {mdb.joint_names[i] for i in j}
    assert len(j) == 55 - 1 - 8
    assert {"left_wrist", "right_wrist", "head", "spine1", "left_index3"} <= names
    assert not names & {"pelvis", "left_hip", "right_knee", "left_ankle", "right_foot"}


def test_metric_positions_remove_horizontal_root_only():
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(5, 4, 3))
    out = E.metric_positions(pos, 0)
    np.testing.assert_allclose(out[:, 0, [0, 2]], 0)
    np.testing.assert_allclose(out[..., 1], pos[..., 1])
    np.testing.assert_allclose(out[:, 2] - out[:, 1], pos[:, 2] - pos[:, 1])


# ------------------------------------------------------------------ Table 2
@pytest.fixture(scope="module")
def controls_report(mirror_db_path, scott_dir):
    with gesturedb.open(mirror_db_path) as db:
        return E.evaluate_controls(db, scott_dir / "inputs" / "2_scott_0_2_2.wav")


def test_controls_table_moves_every_variable_the_requested_way(controls_report, mdb):
    rep = controls_report
    rows = {r.case.name: r for r in rep.rows}
    assert list(rows) == [c.name for c in E.TABLE2_CASES]
    # the paper's four wrist controls must work; symmetric/asymmetric too on this database
    for name in ("wrist high", "wrist low", "wrist fast", "wrist slow", "asymmetric", "symmetric"):
        r = rows[name]
        assert r.status == "PASS", rep.to_text()
        assert (r.mean - r.free_mean) * r.case.direction > 0
        # the share of output frames past the threshold grows under control
        assert r.in_range > r.free_in_range + 0.1
    # thresholds are the database percentiles, shown in cm like the paper
    lwh = np.asarray(mdb.controls["left_wrist_height"], dtype=np.float64)
    assert rows["wrist high"].threshold == pytest.approx(np.percentile(lwh, 85))
    assert rows["wrist low"].threshold == pytest.approx(np.percentile(lwh, 15))
    d = rows["wrist high"].to_dict()
    assert d["unit"] == "cm" and d["threshold"] == pytest.approx(100 * np.percentile(lwh, 85))
    assert rows["wrist fast"].to_dict()["unit"] == "cm/s"
    assert rep.passed and "all checks passed" in rep.to_text()


def test_controls_stats_are_recomputed_on_the_output(controls_report, mdb, scott_dir):
    from gesturedb.features.controls import control_features
    from gesturedb.synth import Searcher

    res = Searcher(mdb).synthesize(scott_dir / "inputs" / "2_scott_0_2_2.wav", control="left_wrist_speed < p15",
                                   keywords=False)
    v = control_features(res.positions, joints=E.feature_joint_indices(mdb), fps=mdb.fps)["left_wrist_speed"]
    row = next(r for r in controls_report.rows if r.case.name == "wrist slow")
    assert row.mean == pytest.approx(float(np.mean(v, dtype=np.float64)), rel=1e-6)
    assert row.std == pytest.approx(float(np.std(v, dtype=np.float64)), rel=1e-5)
    assert row.n_steps == len(res.steps) and row.min_candidates >= 1


def test_controls_checks_can_fail_and_empty_steps_are_reported(mdb, scott_dir):
    cases = [E.TABLE2_CASES[0], E.ControlCase("wrist very high", "left_wrist_height", "left_wrist_height > p99.9", +1)]
    rep = E.evaluate_controls(mdb, scott_dir / "inputs" / "2_scott_0_4_4.wav", cases=cases, min_std_ratio=50.0)
    high, very = rep.rows
    assert high.direction_ok and not high.no_freeze_ok and high.status == "FAIL"
    assert very.status == "EMPTY" and "no candidate" in very.error
    assert not rep.passed
    text = rep.to_text()
    assert "FAILED: wrist high (FAIL), wrist very high (EMPTY)" in text
    md = rep.to_markdown()
    assert md.count("\n|") >= 4 and "EMPTY" in md
    d = rep.to_dict()
    assert d["rows"][1]["mean"] is None and d["passed"] is False
    json.dumps(d)  # NaN became None: valid JSON
    with pytest.raises(ParameterError, match="freeze_reference"):
        E.evaluate_controls(mdb, scott_dir / "inputs" / "2_scott_0_4_4.wav", freeze_reference="median")


# ------------------------------------------------------------------ held-out metrics
def test_holdout_has_every_system_and_the_ground_truth(holdout, scott_dir):
    from gesturedb.io import read_motion

    ev = holdout
    inp = ev.inputs[0]
    assert list(inp.metrics) == list(E.SYSTEMS)
    assert ev.settings["holdout"]["training_frames"] == 2 * 720  # 48 s at 15 fps, mirrored
    # the training database's pose stride, from its own motion (the whole recording's 2 frames)
    assert ev.settings["pose_stride"] == 2 and 0.15 < ev.settings["motion_timescale_s"] < 0.18
    assert f"pose frames 2 apart (motion timescale {ev.settings['motion_timescale_s']:.3f} s)" in ev.to_text()
    # ground truth = the held-out stretch of the motion capture, independently resampled
    m = read_motion(scott_dir / "2_scott_0_1_1.npz")
    gt = m[int(48 * m.fps):].resample(15.0).positions
    T = inp.n_frames
    from gesturedb.features.audio import n_frames_for_duration

    assert T == min(gt.shape[0], n_frames_for_duration(15.5, 15.0)) == 233
    np.testing.assert_allclose(inp.outputs["ground_truth"].positions, gt[:T], atol=1e-9)
    for name, out in inp.outputs.items():
        assert out.positions.shape == (T, 55, 3), name
    gt_row = inp.metrics["ground_truth"]
    assert gt_row["speed_hellinger_gt"] == 0.0
    for name in E.SYSTEMS[1:]:
        r = inp.metrics[name]
        assert 0 < r["speed_hellinger_gt"] < 1 and 0 <= r["speed_hellinger_db"] < 1
        assert 0 <= r["beat_align"] <= 1 and r["l1_diversity_m"] > 0 and r["seam_ratio"] > 0
    # real motion played back matches the ground truth's speeds better than random windows do
    assert inp.metrics["pose_only"]["speed_hellinger_gt"] < inp.metrics["random"]["speed_hellinger_gt"]
    assert inp.metrics["random"]["average_jerk_m_s3"] > gt_row["average_jerk_m_s3"]


def test_default_search_meets_the_placement_goals_on_the_held_out_stretch(scott_dir):
    """Issue 9's goals, with the default settings (random starts), against the capture it never saw:
    pelvis mean speed within 1.3x, largest per-frame root step within 1.5x and foot skating within
    1.5x, on the mean of 4 starts (seeds 0-3). One start is one path, and on this 15 s stretch the
    pelvis swings 0.13-0.18 m/s from start to start (0.12-0.17 with the past-only pose feature of
    schema 3, whose seed 0 happened to be its slowest): a single start tests the seed more than the
    search. The mean start (the old default) moved the pelvis at 1.41x here."""
    ev = E.evaluate_holdout(scott_dir, 48.0, 63.5, mirror=True, systems=["ground_truth", "ranksum_pose"], starts=4)
    inp = ev.inputs[0]
    assert ev.settings["init"] == "random" and [r["seed"] for r in inp.starts["ranksum_pose"]] == [0, 1, 2, 3]
    gt, got = inp.metrics["ground_truth"], inp.starts_summary()["ranksum_pose"]
    assert got["pelvis_speed_m_s"]["mean"] <= 1.3 * gt["pelvis_speed_m_s"]
    assert got["max_root_step_m"]["mean"] <= 1.5 * gt["max_root_step_m"]
    assert got["foot_skating_m_s"]["mean"] <= 1.5 * gt["foot_skating_m_s"]


def test_holdout_metrics_cross_check_the_metric_functions(holdout):
    from gesturedb.eval import metrics as M

    ev = holdout
    inp = ev.inputs[0]
    joints = np.asarray(ev.settings["joints"])
    for name in ("ground_truth", "ranksum_pose"):
        pos = inp.outputs[name].positions.copy()
        pos[:, :, [0, 2]] -= pos[:, ev.root:ev.root + 1, [0, 2]]
        assert inp.metrics[name]["average_jerk_m_s3"] == pytest.approx(M.average_jerk(pos, fps=15, joints=joints))
    gt_pos = E.metric_positions(inp.outputs["ground_truth"].positions, ev.root)
    sys_pos = E.metric_positions(inp.outputs["random"].positions, ev.root)
    assert inp.metrics["random"]["speed_hellinger_gt"] == pytest.approx(
        M.speed_hellinger(sys_pos, gt_pos, fps=15, joints=joints))
    # all systems switch windows at the same frames; the ground truth is measured there too
    b = inp.outputs["ranksum_pose"].boundaries
    np.testing.assert_array_equal(b, np.arange(8, inp.n_frames, 8))
    assert inp.metrics["ground_truth"]["seam_ratio"] == pytest.approx(
        M.seam_jerk(gt_pos, fps=15, boundaries=b, joints=joints)["ratio"])
    # FGD*: the evaluation's encoder, recomputed from the codes of the two outputs
    fgd = ev.reference.get("fgd")
    if fgd is not None:
        from gesturedb.eval.fgd import frechet_distance

        assert inp.metrics["ground_truth"]["fgd_self_gt"] == pytest.approx(0.0, abs=1e-6)
        assert inp.metrics["random"]["fgd_self_gt"] == pytest.approx(
            frechet_distance(fgd.codes(sys_pos), fgd.codes(gt_pos)))
        assert inp.metrics["random"]["fgd_self_db"] == pytest.approx(frechet_distance(fgd.codes(sys_pos), fgd.db_codes))
        assert all(inp.metrics[n]["fgd_self_gt"] > 0 for n in E.SYSTEMS[1:])


def test_holdout_report_files(holdout, tmp_path):
    written = holdout.write(tmp_path / "rep", render=False)
    names = {p.name for p in written}
    assert {"metrics.json", "metrics.txt", "index.html", "speed_0.png", "wrist_0.png", "summary_0.png"} <= names
    d = json.loads((tmp_path / "rep" / "metrics.json").read_text())
    assert d["mode"] == "holdout" and set(d["inputs"][0]["metrics"]) == set(E.SYSTEMS)
    assert d["reference"]["speed_hellinger_gt"] is None
    txt = (tmp_path / "rep" / "metrics.txt").read_text()
    assert "ground truth" in txt and "H(speed) vs GT" in txt
    html = (tmp_path / "rep" / "index.html").read_text()
    for f in ("speed_0.png", "wrist_0.png", "summary_0.png", "metrics.json"):
        assert f in html
    assert html.count("<tr") >= 8


def test_evaluate_inputs_without_ground_truth(mdb, scott_dir):
    ev = E.evaluate_inputs(mdb, [scott_dir / "inputs" / "2_scott_0_4_4.wav"], systems=["random", "ranksum_pose"])
    row = ev.inputs[0].metrics
    assert list(row) == ["random", "ranksum_pose"]
    assert np.isnan(row["random"]["speed_hellinger_gt"]) and row["random"]["speed_hellinger_db"] > 0
    assert "H(speed) vs GT" not in ev.to_text() and "H(speed) vs DB" in ev.to_text()
    ref = ev.reference_row()
    from gesturedb.eval import metrics as M

    joints = np.asarray(ev.settings["joints"])
    parts = [E.metric_positions(mdb.joint_positions[r.start_frame:r.stop_frame], ev.root) for r in mdb.recordings]
    want = sum(M.average_jerk(p, fps=15, joints=joints) * len(p) for p in parts) / sum(len(p) for p in parts)
    assert ref["average_jerk_m_s3"] == pytest.approx(want)
    with pytest.raises(ParameterError, match="no ground truth"):
        E.evaluate_inputs(mdb, [scott_dir / "inputs" / "2_scott_0_4_4.wav"], systems=["ground_truth"])
    with pytest.raises(ParameterError, match="systems: expected names"):
        E.synthesize_systems(mdb, np.zeros(16000, np.float32), 16000, systems=["oracle"])


def test_random_starts_are_independent_runs_from_each_seed(mdb, scott_dir):
    from gesturedb.eval import metrics as M
    from gesturedb.eval import strokes as ST
    from gesturedb.eval.common import feature_joint_indices
    from gesturedb.eval.placement import world_metrics
    from gesturedb.eval.rhythm import input_words, rhythm_agreement
    from gesturedb.io import read_audio
    from gesturedb.synth import Searcher

    wav = scott_dir / "inputs" / "2_scott_0_4_4.wav"
    ev = E.evaluate_inputs(mdb, [wav], systems=["random", "ranksum_pose"], starts=2)
    inp = ev.inputs[0]
    assert list(inp.starts) == ["ranksum_pose"]  # the search's systems only, not the baselines
    rows = inp.starts["ranksum_pose"]
    assert [r["seed"] for r in rows] == [0, 1] and ev.settings["starts"] == 2
    # every row is the metrics of a synthesis run by hand from that random start
    y, sr = read_audio(wav, sr=16000)
    joints = np.asarray(ev.settings["joints"])
    T = inp.n_frames
    for r in rows:
        res = Searcher(mdb).synthesize(y, sr=sr, init="random", seed=r["seed"])
        pos = res.positions[:T]
        assert r["pelvis_speed_m_s"] == pytest.approx(
            world_metrics(pos, fps=15, names=mdb.joint_names)["pelvis_speed_m_s"])
        assert r["average_jerk_m_s3"] == pytest.approx(
            M.average_jerk(E.metric_positions(pos, ev.root), fps=15, joints=joints))
        # the strokes and the rhythm per start, the acceptance numbers of the strokes issue, from their own functions
        arms = ST.band_groups(mdb.joint_names)["arms"]
        assert r["band_arms_2-4_db"] == pytest.approx(
            ST.band_power(pos, fps=15, joints=arms, root=ev.root)["2-4"] / ev.reference["band_power"]["arms"]["2-4"])
        ws, we = input_words(y, sr, inp.transcript)
        rhythm = rhythm_agreement(pos, word_start_s=ws, word_end_s=we, fps=15, joints=feature_joint_indices(mdb),
                                  gap_s=float(mdb.config.get("gap_s", 0.4)))
        assert r["rhythm_hamming"] == pytest.approx(rhythm["rhythm_hamming"])
        assert r["rhythm_beyond_chance"] == pytest.approx(rhythm["rhythm_beyond_chance"])
    # two starts take two paths through the database; the main run is the default start's, seed 0's
    assert rows[0]["pelvis_speed_m_s"] != rows[1]["pelvis_speed_m_s"]
    assert inp.metrics["ranksum_pose"]["pelvis_speed_m_s"] == rows[0]["pelvis_speed_m_s"]
    assert inp.metrics["ranksum_pose"]["rhythm_beyond_chance"] == rows[0]["rhythm_beyond_chance"]
    # and the mean start (--init mean) is a third path
    mean_run = E.evaluate_inputs(mdb, [wav], systems=["ranksum_pose"], init="mean").inputs[0]
    assert mean_run.metrics["ranksum_pose"]["pelvis_speed_m_s"] not in [r["pelvis_speed_m_s"] for r in rows]
    v = [r["pelvis_speed_m_s"] for r in rows]
    assert inp.starts_summary()["ranksum_pose"]["pelvis_speed_m_s"] == pytest.approx(
        dict(mean=np.mean(v), sd=np.std(v), min=min(v), max=max(v)))
    txt = ev.to_text()
    part = txt[txt.index("from 2 random starting poses"):]
    assert "rank-sum, pose pre-selection, random start (seed 0)" in part and "2 random starts" in part
    assert all(h in part for h in ("BeatAlign", "rhythm Ham", "rhythm beyond", "seam/inside", "arms 2-4 / DB",
                                   "hands 4-7 / DB"))
    # the report page splits the starts' columns into tables of even widths, every column once
    from gesturedb.eval.report import STARTS_PER_TABLE, _starts_html

    page = _starts_html(ev, inp)
    widths = [t.split("</tr>")[0].count("<th>") - 1 for t in page.split("<table>")[1:]]
    assert sum(widths) == len(ev.starts_columns(inp)) and max(widths) - min(widths) <= 1
    assert max(widths) <= STARTS_PER_TABLE and page.count("rhythm Ham") == page.count("rhythm beyond") == 1
    assert "vs GT" not in part  # no ground truth for new speech: no column of NaNs
    d = json.loads(json.dumps(ev.to_dict()))
    assert [r["seed"] for r in d["inputs"][0]["starts"]["ranksum_pose"]] == [0, 1]
    assert d["inputs"][0]["starts_summary"]["ranksum_pose"]["pelvis_speed_m_s"]["max"] == pytest.approx(max(v))
    for bad in (-1, 1.5, True):
        with pytest.raises(ParameterError, match="starts: expected an int >= 0"):
            E.evaluate_inputs(mdb, [wav], systems=["ranksum_pose"], starts=bad)


def test_holdout_split_errors(scott_dir):
    from gesturedb.db.build import RecordingSource

    src = RecordingSource("r", "m.npz", "a.wav", None)
    parts = E.holdout_split(src, 10.0, 20.0, 63.5)
    assert [p.span_s for p in parts] == [(0.0, 10.0), (20.0, 63.5)] and parts[0].name == "r[0-10s]"
    assert [p.span_s for p in E.holdout_split(src, 0.0, 63.5, 63.5)] == []
    with pytest.raises(ParameterError, match="past the end"):
        E.holdout_split(src, 70.0, 80.0, 63.5)
    with pytest.raises(ParameterError, match="recording: expected one of"):
        E.evaluate_holdout(scott_dir, 48, 63.5, recording="nope")
    with pytest.raises(ParameterError, match="nothing left"):
        E.evaluate_holdout(scott_dir, 0, 63.5)
