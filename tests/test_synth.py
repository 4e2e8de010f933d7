"""End-to-end synthesis on the real BEAT2 database and held-out speech."""
from __future__ import annotations

import json

import numpy as np
import pytest
import soundfile as sf

from gesturedb.errors import ParameterError, SearchError
from gesturedb.features.audio import n_frames_for_duration
from gesturedb.synth import Searcher

HELD_OUT = "inputs/2_scott_0_2_2"


@pytest.fixture()
def speech(scott_dir):
    return scott_dir / f"{HELD_OUT}.wav"


def test_output_is_exactly_as_long_as_the_audio(scott_db, speech):
    res = Searcher(scott_db).synthesize(speech)
    dur = sf.info(str(speech)).duration
    assert res.n_frames == n_frames_for_duration(dur, scott_db.fps)
    assert res.motion.rotations.shape[0] == res.n_frames
    assert res.positions.shape == (res.n_frames, 55, 3)
    assert np.isfinite(res.positions).all()
    # the last partial window ends exactly at the last frame
    assert res.steps[-1]["out_end"] == res.n_frames
    assert [s["out_start"] for s in res.steps] == list(range(0, res.n_frames, 8))


def test_provenance_names_where_every_frame_came_from(scott_db, speech, tmp_path):
    res = Searcher(scott_db).synthesize(speech)
    rec = scott_db.recordings[0]
    for s in res.steps:
        a, b = s["out_start"], s["out_end"]
        frames = res.source_frames[a:b]
        # a window is a contiguous stretch of one recording, starting at db_frame
        assert np.array_equal(frames, np.arange(s["db_frame"], s["db_frame"] + b - a))
        assert s["recording"] == rec.name
        assert s["source_start_s"] == pytest.approx((s["db_frame"] - rec.start_frame) / scott_db.fps, abs=1e-3)
        seg = s["segment"]
        assert scott_db.chunks.start[seg] + s["segment_start"] == s["db_frame"]
        assert 1 <= s["segment_start"] <= scott_db.chunks.length[seg] - (b - a)
        assert 0 <= s["pose_rank"] < s["candidates"] and 0 <= s["audio_rank"] < s["candidates"]
    path = tmp_path / "p.json"
    res.write_provenance(path)
    assert json.loads(path.read_text())["steps"][3] == res.steps[3]


def test_without_seam_treatment_windows_are_exact_copies(scott_db, speech):
    from gesturedb.synth.contacts import leg_joints

    res = Searcher(scott_db).synthesize(speech, seam_decay_s=0, smooth=False)
    # the legs are bent by the foot-contact IK; every other joint is the database's
    keep = np.setdiff1d(np.arange(1, scott_db.skeleton.n_joints), leg_joints(scott_db.skeleton).ravel())
    body = np.asarray(scott_db.local_rotations[res.source_frames][:, keep], dtype=np.float64)
    np.testing.assert_allclose(res.motion.rotations[:, keep], body, atol=1e-6)


def test_frames_further_from_a_seam_than_the_decay_are_the_source_frames(scott_db, speech):
    """Inertialization is local: with a 0.1 s base decay a seam's offset lasts at most 0.3 s (the adaptive
    decay's cap, 5 frames at 15 fps), so frames 5..7 of every 8-frame window are exactly the placed
    database frames, and the frames right after a seam are not."""
    from gesturedb.synth.assemble import MAX_DECAY_FACTOR
    from gesturedb.synth.contacts import leg_joints
    from gesturedb.synth.seams import decay_frames

    s = Searcher(scott_db)
    res = s.synthesize(speech, seam_decay_s=0.1)
    nd = decay_frames(MAX_DECAY_FACTOR * 0.1, scott_db.fps)
    assert nd == 5
    keep = np.setdiff1d(np.arange(1, scott_db.skeleton.n_joints), leg_joints(scott_db.skeleton).ravel())
    placed = s.synthesize(speech, seam_decay_s=0)  # the same windows, placed, no seam treatment
    assert np.array_equal(placed.source_frames, res.source_frames)
    body = placed.motion.rotations[:, keep]
    starts = np.concatenate([[0], res.boundaries])
    since = np.arange(res.n_frames) - starts[np.searchsorted(starts, np.arange(res.n_frames), side="right") - 1]
    far = (since >= nd) | (np.arange(res.n_frames) < starts[1])
    assert far.sum() > res.n_frames / 4
    np.testing.assert_array_equal(res.motion.rotations[far][:, keep], body[far])
    near = ~far
    assert np.abs(res.motion.rotations[near][:, keep] - body[near]).max() > 1e-3


def _seam_jerk(positions, boundaries, fps):
    """Mean |jerk| of the wrists at window boundaries (frames b-1..b+1)."""
    p = positions[:, [20, 21]]
    jerk = np.linalg.norm(np.diff(p, n=3, axis=0), axis=-1).mean(-1) * fps ** 3
    idx = np.concatenate([boundaries - 2, boundaries - 1, boundaries])
    idx = idx[(idx >= 0) & (idx < jerk.shape[0])]
    return jerk[idx].mean()


def test_inertialized_seams_have_the_jerk_of_the_inside(scott_db, speech):
    from gesturedb.eval.metrics import seam_jerk

    s = Searcher(scott_db)
    hard = s.synthesize(speech, seam_decay_s=0)
    soft = s.synthesize(speech)
    assert np.array_equal(hard.source_frames, soft.source_frames)  # same search, only the seams differ
    j_hard = _seam_jerk(hard.positions, hard.boundaries, scott_db.fps)
    j_soft = _seam_jerk(soft.positions, soft.boundaries, scott_db.fps)
    assert j_soft < 0.5 * j_hard, (j_soft, j_hard)
    r = seam_jerk(soft.positions, fps=scott_db.fps, boundaries=soft.boundaries, joints=[18, 19, 20, 21])
    assert r["ratio"] < 1.15, r


def test_default_keeps_the_strokes_of_the_database(scott_db, speech):
    """Arm velocity power in every band within 0.67-1.5x of the database's own motion (the goal of the
    strokes issue), where the old global Savitzky-Golay filter kept a third or less at 4-7 Hz."""
    from gesturedb.eval import strokes as ST

    arms = ST.band_groups(scott_db.joint_names)["arms"]
    ref = ST.pooled_band_power([scott_db.joint_positions.astype(np.float64)], fps=scott_db.fps, joints=arms)
    s = Searcher(scott_db)
    out = ST.band_ratios(ST.band_power(s.synthesize(speech).positions, fps=scott_db.fps, joints=arms), ref)
    assert all(0.6 < v < 1.6 for v in out.values()), out
    smoothed = ST.band_ratios(ST.band_power(s.synthesize(speech, smooth=True).positions, fps=scott_db.fps,
                                            joints=arms), ref)
    assert smoothed["4-7"] < 0.6 * out["4-7"], (smoothed, out)


def test_options_change_the_result_reproducibly(scott_db, speech):
    s = Searcher(scott_db)
    base = s.synthesize(speech)
    k2 = s.synthesize(speech, k=2)
    assert not np.array_equal(base.source_frames, k2.source_frames)
    r1 = s.synthesize(speech, init="random", seed=3)
    r2 = s.synthesize(speech, init="random", seed=3)
    assert np.array_equal(r1.source_frames, r2.source_frames)
    audio_pre = s.synthesize(speech, preselect="audio")
    # audio pre-selection picks windows with audio at least as close on average
    assert np.mean([x["audio_dist"] for x in audio_pre.steps]) <= np.mean([x["audio_dist"] for x in base.steps]) + 1e-6


def test_half_precision_searcher_gives_the_same_result(scott_db, speech):
    a = Searcher(scott_db).synthesize(speech, control="0-20: left_wrist_height > p60")
    b = Searcher(scott_db, half_precision=True).synthesize(speech, control="0-20: left_wrist_height > p60")
    assert np.array_equal(a.source_frames, b.source_frames)
    assert [s["pose_dist"] for s in a.steps] == [s["pose_dist"] for s in b.steps]


def test_samples_and_path_give_the_same_result(scott_db, speech):
    from gesturedb.io import read_audio

    x, sr = read_audio(speech, sr=16000)
    a = Searcher(scott_db).synthesize(speech)
    b = Searcher(scott_db).synthesize(x, sr=sr)
    assert np.array_equal(a.source_frames, b.source_frames)


def test_audio_shorter_than_one_step(scott_db):
    with pytest.raises(ParameterError, match=r"audio: expected at least one search step \(8 frames = 0.53 s\), got 4 frames"):
        Searcher(scott_db).synthesize(np.zeros(int(16000 * 0.27), np.float32), sr=16000)


def test_control_that_leaves_nothing_names_the_step_and_suggests_a_percentile(scott_db, speech):
    # p100 is the database maximum: nothing is strictly above it
    with pytest.raises(SearchError) as info:
        Searcher(scott_db).synthesize(speech, control="1-3: left_wrist_height > p100")
    msg = str(info.value)
    assert msg.startswith("step 2 (output frame 16, t = 1.07 s) has no candidate under control "
                          "'left_wrist_height > p100'"), msg
    assert "'left_wrist_height > p9" in msg and "instead of" in msg and "would leave" in msg, msg
    assert info.value.step == 2


def test_excluding_every_recording_is_a_clear_error(scott_db, speech):
    with pytest.raises(SearchError, match=r"step 0 \(output frame t=0\): no candidate window left: .*excluded"):
        Searcher(scott_db).synthesize(speech, exclude=["2_scott_0_1_1"])


def test_speaker_keeps_facing_forward_and_stays_in_place(scott_db, scott_dir):
    """Windows keep their recording's normalised placement: no heading or position drift over a minute."""
    from gesturedb.features.body import body_frame
    from gesturedb.io.joints import find_joints

    res = Searcher(scott_db).synthesize(scott_dir / "inputs/2_scott_0_4_4.wav")
    joints = find_joints(scott_db.joint_names)
    _, rot = body_frame(res.positions, joints=joints)
    forward = rot[:, :, 2]  # columns: left, up, forward
    heading_deg = np.degrees(np.arctan2(forward[:, 0], forward[:, 2]))
    assert np.abs(heading_deg).max() < 45, np.abs(heading_deg).max()
    # never further from the origin than the recording ever is from its own mean position
    db_xz = scott_db.root_positions[:, [0, 2]].astype(np.float64)
    db_reach = np.linalg.norm(db_xz - db_xz.mean(0), axis=1).max()
    out_reach = np.linalg.norm(res.motion.root_positions[:, [0, 2]], axis=1).max()
    assert out_reach <= db_reach + 0.03, (out_reach, db_reach)  # Savitzky-Golay may overshoot by a few cm


def test_database_without_a_long_enough_segment(scott_dir, tmp_path, speech):
    import gesturedb

    # 8-frame chunks cannot hold an 8-frame window plus its entry frame
    with gesturedb.build([scott_dir], tmp_path / "short.h5", chunk_frames=8) as db:
        with pytest.raises(ParameterError, match=r"short.h5: no chunks segment is long enough for a window of 8 frames "
                                                 r"plus its entry frame \(longest: 8 frames\)"):
            Searcher(db).synthesize(speech)
        # the word-gap clips of the same database are long enough
        assert Searcher(db, segments="clips").synthesize(speech).n_frames > 0
