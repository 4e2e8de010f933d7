"""Placement of pieces in the shared assembly step, foot contacts, and the world-space metrics."""
from __future__ import annotations

import numpy as np
import pytest
import soundfile as sf

from gesturedb import rotations as R
from gesturedb.eval import placement as P
from gesturedb.motion import Motion
from gesturedb.synth import Searcher
from gesturedb.synth.assemble import Piece, assemble_frames, assemble_pieces, foot_contacts, foot_joints
from gesturedb.synth.contacts import leg_joints

# ---------------------------------------------------------------- metric conventions on hand-made signals

def _line(F, v, fps):
    """One joint moving at constant velocity v (m/s) along x: (F, 1, 3)."""
    t = np.arange(F) / fps
    pos = np.zeros((F, 1, 3))
    pos[:, 0, 0] = v * t
    return pos


def test_root_speed_and_step_of_a_constant_velocity():
    pos = _line(30, 0.5, 15.0)
    assert P.root_speed(pos, fps=15.0) == pytest.approx(0.5)
    assert P.max_root_step(pos) == pytest.approx(0.5 / 15.0)
    pos[10:] += [0.3, 0, 0]  # a teleport shows as the largest step
    assert P.max_root_step(pos) == pytest.approx(0.3 + 0.5 / 15.0)


def test_mean_jerk_is_exact_for_a_cubic():
    fps, c = 30.0, 0.7
    t = np.arange(40) / fps
    pos = np.zeros((40, 1, 3))
    pos[:, 0, 1] = c * t ** 3
    assert P.mean_jerk(pos, fps=fps, joints=[0]) == pytest.approx(6 * c, rel=1e-9)
    assert P.mean_jerk(_line(40, 1.0, fps), fps=fps, joints=[0]) == pytest.approx(0.0, abs=1e-9)


def test_foot_skating_counts_only_feet_on_the_floor():
    fps, F = 15.0, 20
    pos = np.zeros((F, 2, 3))  # joint 0 ankle, 1 toe
    pos[:, 0, 0] = 0.2 * np.arange(F) / fps  # sliding at 0.2 m/s on the floor
    pos[:, 1] = pos[:, 0]
    assert P.foot_skating(pos, fps=fps, feet=[[0, 1]]) == pytest.approx(0.2)
    lifted = pos.copy()
    lifted[F // 2:, :, 1] = 0.3  # in the air for the second half: only the first half counts
    lifted[F // 2:, :, 0] += 5.0  # and a huge move in the air changes nothing
    assert P.foot_skating(lifted, fps=fps, feet=[[0, 1]]) == pytest.approx(0.2)


def test_heading_is_zero_facing_plus_z_and_positive_towards_plus_x():
    pos = np.zeros((2, 2, 3))
    pos[:, 0] = [0.1, 0, 0]  # left hip at +x: facing +z
    pos[:, 1] = [-0.1, 0, 0]
    assert np.allclose(P.heading_deg(pos, left_hip=0, right_hip=1), 0.0)
    q = R.from_axis_angle(np.array([0, np.pi / 2, 0]))  # turned 90 degrees about +y: facing +x
    turned = R.apply(np.broadcast_to(q, pos.shape[:-1] + (4,)), pos)
    assert np.allclose(P.heading_deg(turned, left_hip=0, right_hip=1), 90.0)


def test_root_relative_jerk_removes_only_the_roots_horizontal_motion(scott_db):
    pos = np.asarray(scott_db.joint_positions[:200], dtype=np.float64)
    t = np.arange(200) / scott_db.fps  # a sliding root: 5 cm at 1.5 Hz
    slid = pos + 0.05 * np.sin(2 * np.pi * 1.5 * t)[:, None, None] * np.array([1.0, 0, 0.5])
    m, ms = (P.world_metrics(p, fps=scott_db.fps, names=scott_db.joint_names) for p in (pos, slid))
    for g in ("root", "legs", "arms", "hands", "head"):
        assert ms[f"jerk_rel_{g}_m_s3"] == pytest.approx(m[f"jerk_rel_{g}_m_s3"], rel=1e-6)
        assert abs(ms[f"jerk_world_{g}_m_s3"] - m[f"jerk_world_{g}_m_s3"]) > 3.0, g


# ---------------------------------------------------------------- placement

def _recording_piece(db, a, n, *, shift=(0.0, 0.0), turn=0.0):
    rot = np.asarray(db.local_rotations[a:a + n], dtype=np.float64)
    rot /= np.linalg.norm(rot, axis=-1, keepdims=True)
    root = np.asarray(db.root_positions[a:a + n], dtype=np.float64)
    q = R.from_axis_angle(np.array([0, turn, 0]))
    rot[:, 0] = R.multiply(np.broadcast_to(q, rot[:, 0].shape), rot[:, 0])
    root = R.apply(np.broadcast_to(q, root.shape[:-1] + (4,)), root) + [shift[0], 0, shift[1]]
    return rot, root


def test_pieces_from_far_apart_places_do_not_teleport_the_body(scott_db):
    """Each piece continues the output's root: a 2 m, 90-degree jump in the sources is no jump in the output."""
    fps, n = scott_db.fps, 40
    pieces = []
    for i, a in enumerate(range(0, 6 * 97, 97)):
        rot, root = _recording_piece(scott_db, a, n, shift=(2.0 * (i % 2), -1.5 * (i % 3)), turn=np.pi / 2 * (i % 2))
        pieces.append(Piece(out_start=i * n, rotations=rot, root=root))
    src_steps = max(P.max_root_step(np.asarray(scott_db.joint_positions[a:a + n])) for a in range(0, 6 * 97, 97))
    for lock in (False, True):
        m = assemble_pieces(scott_db.skeleton, fps, pieces, smooth=False, lock_feet=lock)
        step = np.linalg.norm(np.diff(m.root_positions, axis=0), axis=-1)
        assert step.max() < max(2 * src_steps, 0.06), (lock, step.max(), src_steps)
    old = assemble_pieces(scott_db.skeleton, fps, pieces, smooth=False, placement="source", seam_decay_s=0)
    assert np.linalg.norm(np.diff(old.root_positions, axis=0), axis=-1).max() > 1.0  # the behaviour that was fixed


def test_placement_keeps_each_pieces_own_displacement_and_turning(scott_db):
    fps, n = scott_db.fps, 60
    rot0, root0 = _recording_piece(scott_db, 0, n)
    rot1, root1 = _recording_piece(scott_db, 300, n, shift=(5.0, 5.0), turn=1.0)
    m = assemble_pieces(scott_db.skeleton, fps, [Piece(0, rot0, root0), Piece(n, rot1, root1)], smooth=False,
                        lock_feet=False)
    # the second piece's own horizontal path length and height are kept (the pulls change them only slightly)
    own = np.linalg.norm(np.diff(root1[:, [0, 2]], axis=0), axis=-1).sum()
    out = np.linalg.norm(np.diff(m.root_positions[n:, [0, 2]], axis=0), axis=-1).sum()
    assert out == pytest.approx(own, rel=0.15, abs=0.01)
    # the height is the piece's own once the seam's offset has decayed (no lead-in: the output went on)
    from gesturedb.synth.seams import SEAM_DECAY_S, decay_frames

    nd = decay_frames(SEAM_DECAY_S, fps)
    np.testing.assert_allclose(m.root_positions[n + nd:, 1], root1[nd:, 1])


def test_a_seam_is_inertialized_and_then_the_piece_is_its_own(scott_db, monkeypatch):
    """Lead-in going +x, new piece going -x: the output keeps the old velocity across the seam, turns
    over the decay, and from then on takes exactly the new piece's own steps.
    """
    import gesturedb.synth.assemble as A

    monkeypatch.setattr(A, "POSITION_PULL_S", 1e12)
    monkeypatch.setattr(A, "HEADING_PULL_S", 1e12)
    from gesturedb.synth.seams import LEAD_FRAMES, decay_frames

    fps, n, v = 15.0, 12, 0.3
    J = len(scott_db.skeleton.names)
    rot = np.zeros((n, J, 4))
    rot[..., 0] = 1.0

    def line(x0, vel, k):
        root = np.zeros((k, 3))
        root[:, 0] = x0 + vel * np.arange(k) / fps
        root[:, 1] = 1.0
        return root

    first = Piece(0, rot, line(0.0, v, n))
    lead = (rot[:LEAD_FRAMES], line(v * n / fps, v, LEAD_FRAMES))  # how the first piece would have gone on
    second = Piece(n, rot, line(7.0, -v, n), lead_in=lead)  # from elsewhere, going back
    decay = 0.4
    nd = decay_frames(decay, fps)
    m = assemble_pieces(scott_db.skeleton, fps, [first, second], smooth=False, lock_feet=False, seam_decay_s=decay)
    step = np.diff(m.root_positions[:, 0])
    np.testing.assert_allclose(step[:n], v / fps, atol=1e-12)  # into the seam: the first piece, and the
    # seam's first step is the first piece's own continuation (velocity runs on across the seam)
    assert step[n - 1] == pytest.approx(v / fps, abs=1e-12)
    np.testing.assert_allclose(step[n + nd:], -v / fps, atol=1e-12)  # after the decay: the second piece's own
    acc = np.diff(step)
    # the turn is spread over the decay, not done in a frame (a one-frame turn changes the step by 2 v / fps)
    assert np.abs(acc).max() < 0.6 * (2 * v / fps)
    np.testing.assert_allclose(m.root_positions[:, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(m.root_positions[:, 1], 1.0, atol=1e-12)


def test_a_seams_rotation_samples_stay_on_the_branch_nearest_each_other():
    """The offset's velocity at a seam comes from three rotation vectors; each is taken on the branch
    (angle a or a - 2 pi about the same axis) nearest the sample before it. Through pi the samples stay
    continuous; turning fast away from a small first offset they are left alone (the rule before moved
    the third to the other branch when it pointed against the first: 64 rad/s instead of 23, and the
    decaying offset spun an elbow by up to 179 degrees a frame on a lively speaker's database)."""
    from gesturedb import rotations as R
    from gesturedb.synth.seams import continuous_rotation_vectors, seam_derivatives

    u = np.array([0.0, 0.6, 0.8])
    through_pi = R.to_axis_angle(R.from_axis_angle(np.array([2.9, 3.1, 3.3])[:, None, None] * u))  # (3, 1, 3)
    assert np.linalg.norm(through_pi[2]) < np.pi  # to_axis_angle wrapped the last one
    np.testing.assert_allclose(continuous_rotation_vectors(through_pi)[:, 0], np.array([2.9, 3.1, 3.3])[:, None] * u,
                               atol=1e-12)
    # the seam that spun the elbow: 0.47, 1.26 and 2.26 rad, each on its own branch already
    fast = np.array([[0.324, 0.008, -0.34], [0.221, -1.219, 0.208], [-0.332, -2.038, 0.923]])[:, None]
    got = continuous_rotation_vectors(fast)
    np.testing.assert_array_equal(got, fast)
    v0 = np.linalg.norm(seam_derivatives(got, 15.0)[1])
    assert v0 == pytest.approx(22.6, abs=0.1)
    # every sample stays the same rotation
    for d in (through_pi, fast):
        same = np.abs((R.from_axis_angle(continuous_rotation_vectors(d)) * R.from_axis_angle(d)).sum(-1))
        np.testing.assert_allclose(same, 1.0, atol=1e-12)


@pytest.fixture(scope="module")
def mirrored_db(scott_dir, tmp_path_factory):
    import gesturedb

    out = tmp_path_factory.mktemp("mirror") / "scott_mirror.h5"
    gesturedb.build([scott_dir], out, mirror=True).close()
    with gesturedb.open(out) as db:
        yield db


@pytest.mark.parametrize("which", ["scott", "mirrored"])
def test_planted_feet_stay_planted(scott_db, mirrored_db, which):
    """Where a source foot is planted, the output's ankle barely moves horizontally; the mirrored copy
    (second recording of the mirrored database) alone as well."""
    rng = np.random.default_rng(3)
    db = scott_db if which == "scott" else mirrored_db
    lo = 1 if which == "scott" else db.recordings[1].start_frame + 1
    T, step = 400, 8
    starts = np.arange(0, T, step)
    src = np.concatenate([np.arange(s, s + step) for s in rng.integers(lo, db.n_frames - step - 10, len(starts))])
    feet = foot_joints(db.skeleton)
    src_pos = np.asarray(db.joint_positions[src], dtype=np.float64)
    planted = foot_contacts(src_pos, fps=db.fps, feet=feet, floor_y=float(src_pos[:, feet, 1].min()))
    both = planted[1:] & planted[:-1]
    speeds = {}
    for lock in (False, True):
        m = assemble_frames(db, src, starts, lock_feet=lock)
        ank = m.positions[:, feet[:, 0]][:, :, [0, 2]]
        v = np.linalg.norm(np.diff(ank, axis=0), axis=-1) * db.fps
        speeds[lock] = float(v[both].mean())
    assert both.sum() > 50
    assert speeds[True] < 0.6 * speeds[False], speeds
    assert speeds[True] < 0.12, speeds


def test_no_foot_goes_under_the_floor_and_feet_above_it_are_untouched(scott_db):
    """A root lowered by 15 cm over a standing stretch (what a seam's offset did after a crouch): the leg IK
    bends the knees so that no foot goes under the floor; frames whose feet stay above it keep their
    rotations bit for bit; pushing the frames in blocks gives the same bits as at once."""
    from gesturedb.synth.contacts import FootPlanter

    db = scott_db
    src = np.arange(200, 320)
    rot = np.asarray(db.local_rotations[src], dtype=np.float64)
    root = np.asarray(db.root_positions[src], dtype=np.float64)
    feet = foot_joints(db.skeleton)
    floor = float(np.asarray(db.joint_positions[src])[:, feet, 1].min())
    dip = 0.15 * np.sin(np.pi * np.clip((np.arange(120) - 40) / 30.0, 0, 1))  # frames 40-70 go down and up
    low_root = root - dip[:, None] * [0, 1, 0]
    none = np.zeros((120, 2), dtype=bool)  # no contacts: only the floor acts
    out = FootPlanter(db.skeleton, db.fps, floor_y=floor).push(rot, low_root, none, final=True)
    pos = Motion(skeleton=db.skeleton, fps=db.fps, rotations=out, root_positions=low_root).positions
    before = Motion(skeleton=db.skeleton, fps=db.fps, rotations=rot, root_positions=low_root).positions
    assert before[:, feet, 1].min() < floor - 0.1  # the dip puts them well under
    assert pos[:, feet, 1].min() >= floor - 1e-6
    under = (before[:, feet, 1].min(axis=2) < floor).any(axis=1)
    assert under.sum() > 10
    np.testing.assert_array_equal(out[~under], rot[~under])
    # only the legs move
    keep = np.setdiff1d(np.arange(db.skeleton.n_joints), leg_joints(db.skeleton).ravel())
    np.testing.assert_array_equal(out[:, keep], rot[:, keep])
    # streamed in blocks: the same bits
    fp = FootPlanter(db.skeleton, db.fps, floor_y=floor)
    parts = [fp.push(rot[i:i + 17], low_root[i:i + 17], none[i:i + 17]) for i in range(0, 120, 17)]
    parts.append(fp.push(rot[:0], low_root[:0], none[:0], final=True))
    np.testing.assert_array_equal(np.concatenate(parts), out)


def _drifting_foot(T=90, v=0.01):
    """An ankle that creeps along x at v m per frame (the body moving over a planted foot), planted throughout."""
    free = np.zeros((T, 3))
    free[:, 0] = v * np.arange(T)
    free[:, 1] = 0.08
    return free, np.ones(T, dtype=bool)


def test_a_planted_ankle_holds_its_anchor_then_steps_without_a_jump():
    from gesturedb.synth import contacts as C

    free, planted = _drifting_foot()
    target, weight = C._ankle_targets(free, planted)
    assert weight.all()
    step = np.linalg.norm(np.diff(target[:, [0, 2]], axis=0), axis=-1)
    held = step < 1e-12
    # most frames hold still; the anchor never lags the motion by more than the drift bound plus one frame's creep
    assert held.mean() > 0.6
    assert np.linalg.norm((target - free)[:, [0, 2]], axis=-1).max() <= C.MAX_ANCHOR_DRIFT_M + 0.01 + 1e-9
    # steps: no frame moves more than the step's distance spread over its frames (a sampled smoothstep peaks
    # at about 1.5x the mean)
    dist = C.MAX_ANCHOR_DRIFT_M + 0.01 * C.STEP_FRAMES + 0.01
    assert step.max() <= 1.6 * dist / C.STEP_FRAMES, step.max()
    # and a stepping ankle lifts (at most STEP_HEIGHT_M) while a held one stays at the motion's height
    lift = target[:, 1] - free[:, 1]
    assert lift.max() == pytest.approx(C.STEP_HEIGHT_M, rel=0.1)
    assert lift.min() >= -1e-12
    assert not np.any(held & (lift[1:] > 0) & (lift[:-1] > 0))  # a lifted ankle is always moving


def test_a_released_ankle_glides_to_the_motion_and_follows_it():
    """A foot that lifts and does not come down within a step's frames glides from its anchor to where the
    motion has it a step's frames on, and follows the motion from there."""
    from gesturedb.synth import contacts as C

    free, planted = _drifting_foot(T=40)
    planted[10:] = False
    target, weight = C._ankle_targets(free, planted)
    np.testing.assert_allclose(target[:10, 0], free[0, 0])           # held where the contact began
    last = 10 + C.STEP_FRAMES - 1
    assert weight[10:last + 1].all() and not weight[last + 1:].any()
    gap = np.abs(target[10:last + 1, 0] - free[10:last + 1, 0])
    # the foot starts from rest (the smoothstep's zero slope), so its lag grows by at most a frame's creep, then
    # shrinks every frame...
    assert gap.max() <= gap[0] + 0.01 and np.all(np.diff(gap[2:]) < 0)
    np.testing.assert_allclose(target[last:], free[last:])            # ...to none


def test_a_lifted_foot_glides_straight_to_where_it_lands():
    """Between two contacts the ankle goes straight from its anchor to the landing, however the motion
    sweeps it in between (a seam's offset on the legs): its horizontal path is the distance between the
    two, and the next contact holds it where it landed."""
    from gesturedb.synth import contacts as C

    T = 40
    free = np.zeros((T, 3))
    free[:, 1] = 0.08
    free[:, 0] = np.where(np.arange(T) < 16, 0.0, 0.25)              # the foot steps 0.25 m along x ...
    free[10:16, 2] = 0.1 * np.sin(np.linspace(0, np.pi, 6))           # ... swept 0.1 m sideways on the way
    planted = np.ones(T, dtype=bool)
    planted[10:16] = False
    target, weight = C._ankle_targets(free, planted)
    assert weight.all()
    path = np.linalg.norm(np.diff(target[:, [0, 2]], axis=0), axis=-1)
    assert path.sum() == pytest.approx(0.25, abs=1e-9)
    np.testing.assert_allclose(target[-5:, [0, 2]], free[-5:, [0, 2]], atol=1e-12)
    # no faster than a step of the largest drift (a sampled smoothstep peaks at about 1.5x the mean)
    assert path.max() <= 1.6 * C.MAX_ANCHOR_DRIFT_M / C.STEP_FRAMES
    # the way is a step's: lifted in its middle by up to a step's height (the motion's foot stayed at 8 cm)
    assert target[9:, 1].max() > 0.08 + 0.5 * C.STEP_HEIGHT_M and target[9:, 1].max() <= 0.08 + C.STEP_HEIGHT_M + 1e-12
    # the free path would have gone 0.25 m plus the sweep: gliding is shorter
    assert np.linalg.norm(np.diff(free[:, [0, 2]], axis=0), axis=-1).sum() > path.sum() + 0.1


def test_a_planted_ankle_holds_one_height_through_its_contact():
    """A seam's offset moves the root up and down for a fraction of a second: a planted ankle settles down
    with the motion over its contact's first release of frames (a foot comes down on its toe or heel, ankle
    still high), keeps that height for the rest of the contact (the knee bends instead), and after the
    contact returns to the motion's height over half a release, without a jump."""
    from gesturedb.synth import contacts as C

    T = 60
    free = np.zeros((T, 3))
    free[:, 1] = 0.08 + 0.03 * np.sin(np.arange(T) / 3.0)  # bobbing by 3 cm
    planted = np.ones(T, dtype=bool)
    planted[40:] = False
    target, weight = C._ankle_targets(free, planted)
    R = C.RELEASE_FRAMES
    np.testing.assert_allclose(target[:R, 1], np.minimum.accumulate(free[:R, 1]))
    np.testing.assert_allclose(target[R:40, 1], free[:R, 1].min())
    assert free[:40, 1].min() < free[:R, 1].min() - 0.005  # later dips do not move it
    after = 40 + C.STEP_FRAMES
    np.testing.assert_allclose(target[after:], free[after:])
    # no jump: the release spreads the gap over half its frames (a sampled smoothstep peaks at about 1.5x the mean)
    gap = abs(free[40, 1] - target[39, 1])
    assert (np.abs(np.diff(target[:, 1])).max()
            <= 1.6 * gap / (C.RELEASE_FRAMES / 2 + 1) + np.abs(np.diff(free[:, 1])).max())


def test_holding_feet_adds_no_ankle_jump_on_real_speech(scott_db, scott_dir):
    """On real speech the leg IK (holds, steps, releases, re-plants) makes no ankle jump: in one frame no
    ankle moves much further than the motion without it already does (a re-plant during a release once
    jumped 0.22 m)."""
    audio, sr = sf.read(str(scott_dir / "inputs" / "2_scott_0_2_2.wav"), dtype="float32")
    res = Searcher(scott_db).synthesize(audio, sr=sr)
    feet = foot_joints(scott_db.skeleton)
    starts = np.r_[0, res.boundaries]
    steps = {}
    for lock in (False, True):
        m = assemble_frames(scott_db, res.source_frames, starts, lock_feet=lock)
        steps[lock] = np.linalg.norm(np.diff(m.positions[:, feet[:, 0]], axis=0), axis=-1)
    np.testing.assert_allclose(m.positions, res.positions)  # the synthesis is this assembly
    # a foot held a little longer catches up within the source's own step (0.114 against 0.096 m in a
    # frame at the fastest, in a step of the speaker's), never a jump out of place (0.22 m once, 2.3x)
    assert steps[True].max() <= 1.25 * steps[False].max(), (steps[True].max(), steps[False].max())
    assert np.percentile(steps[True], 99) <= 1.1 * np.percentile(steps[False], 99)


def test_leg_ik_only_touches_the_legs(scott_db):
    db = scott_db
    src = np.arange(100, 260)
    starts = np.array([0, 40, 80, 120])
    a = assemble_frames(db, src, starts, lock_feet=False)
    b = assemble_frames(db, src, starts, lock_feet=True)
    keep = np.setdiff1d(np.arange(1, db.skeleton.n_joints), leg_joints(db.skeleton).ravel())
    np.testing.assert_allclose(a.rotations[:, keep], b.rotations[:, keep], atol=1e-9)
    # the leg bones keep their lengths
    for hip, knee, ankle in leg_joints(db.skeleton):
        for u, v in ((hip, knee), (knee, ankle)):
            la = np.linalg.norm(a.positions[:, u] - a.positions[:, v], axis=-1)
            lb = np.linalg.norm(b.positions[:, u] - b.positions[:, v], axis=-1)
            np.testing.assert_allclose(la, lb, atol=1e-6)


def _ik_case(db, n=240, seed=0):
    """Real poses of ``db`` and ankle targets around them (some out of reach, some on the hip, one leg
    straight): the arguments of two_bone_ik for its left leg."""
    rng = np.random.default_rng(seed)
    frames = np.arange(100, 100 + n)
    m = Motion(skeleton=db.skeleton, fps=db.fps, rotations=np.asarray(db.rows("local_rotations", frames), np.float64),
               root_positions=np.asarray(db.rows("root_positions", frames), np.float64))
    pos, grot = m.forward_kinematics()
    hip, knee, ankle = (int(j) for j in leg_joints(db.skeleton)[0])
    target = pos[:, ankle] + rng.normal(scale=0.1, size=(n, 3))
    target[::7] += rng.normal(scale=1.0, size=(len(target[::7]), 3))  # beyond the leg's reach
    target[3] = pos[3, hip]  # on the hip
    target[5] = pos[5, ankle]  # where the ankle is
    return m.rotations, grot, pos, dict(hip=hip, knee=knee, ankle=ankle, target=target)


def test_leg_ik_in_cpp_equals_the_numpy_reference(scott_db):
    """csrc/ik.cpp against contacts._two_bone_ik_numpy (float64 numpy, not the code under test): equal
    to rounding (libm's acos and sin against numpy's), and the ankle reaches reachable targets."""
    from gesturedb.synth.contacts import _two_bone_ik_numpy, two_bone_ik

    rot, grot, pos, kw = _ik_case(scott_db)
    got = two_bone_ik(rot, grot, pos, **kw)
    want = _two_bone_ik_numpy(rot, grot, pos, **kw)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    changed = np.setdiff1d(np.arange(rot.shape[1]), [kw["hip"], kw["knee"], kw["ankle"]])
    assert np.array_equal(got[:, changed], rot[:, changed])
    # a straight leg (no bend plane) takes the hip's x axis, as numpy does
    straight = rot.copy()
    straight[:, kw["knee"]] = [1.0, 0.0, 0.0, 0.0]
    m = Motion(skeleton=scott_db.skeleton, fps=scott_db.fps, rotations=straight, root_positions=np.zeros((len(rot), 3)))
    s_pos, s_grot = m.forward_kinematics()
    s_kw = dict(kw, target=s_pos[:, kw["ankle"]] + 0.05)
    np.testing.assert_allclose(two_bone_ik(straight, s_grot, s_pos, **s_kw),
                               _two_bone_ik_numpy(straight, s_grot, s_pos, **s_kw), rtol=0, atol=1e-12)


def test_leg_ik_in_cpp_is_per_frame_and_says_what_it_expected(scott_db):
    """Frames alone, in blocks or all at once: the same bits (the stream and the offline synthesis split
    them differently). Wrong shapes and joints are refused with what was expected."""
    from gesturedb.errors import ParameterError
    from gesturedb.synth.contacts import two_bone_ik

    rot, grot, pos, kw = _ik_case(scott_db, n=50)
    whole = two_bone_ik(rot, grot, pos, **kw)
    for cuts in ([1], [3, 8, 9], [17, 33]):
        parts = []
        for a, b in zip([0] + cuts, cuts + [len(rot)]):
            parts.append(two_bone_ik(rot[a:b], grot[a:b], pos[a:b], **dict(kw, target=kw["target"][a:b])))
        assert np.array_equal(np.concatenate(parts), whole)
    with pytest.raises(ParameterError, match=r"target: expected \(50, 3\); got \(49, 3\)"):
        two_bone_ik(rot, grot, pos, **dict(kw, target=kw["target"][1:]))
    with pytest.raises(ParameterError, match=r"positions: expected \(50, \d+, 3\); got"):
        two_bone_ik(rot, grot, pos[:, :-1], **kw)
    with pytest.raises(ParameterError, match=r"knee: expected a joint in \[0, \d+\); got 999"):
        two_bone_ik(rot, grot, pos, **dict(kw, knee=999))


def test_seam_offsets_in_cpp_equal_the_numpy_composition(scott_db):
    """csrc/seams.cpp against quintic_offsets then apply_rotation_offsets (numpy, float64): equal to
    rounding, exactly the rotations from the decay on, the same bits in any split of the frames; one
    decay for all joints or one per joint; shapes refused with what was expected."""
    from gesturedb.errors import ParameterError
    from gesturedb.synth.seams import apply_quintic_rotation_offsets, apply_rotation_offsets, quintic_offsets

    rng = np.random.default_rng(3)
    J = scott_db.skeleton.n_joints
    q = R.normalize(rng.normal(size=(30, J, 4)))
    x0, v0, a0 = rng.normal(scale=0.3, size=(J, 3)), rng.normal(size=(J, 3)), rng.normal(scale=5.0, size=(J, 3))
    x0[4] = v0[4] = a0[4] = 0.0  # a joint without offset: its rotation unchanged
    t = np.arange(30) / 15.0
    for decay in (8 / 15, rng.uniform(0.3, 1.6, size=(J, 1)), rng.uniform(0.3, 1.6, size=J)):
        got = apply_quintic_rotation_offsets(x0, v0, a0, decay, t, q)
        want = apply_rotation_offsets(quintic_offsets(x0, v0, a0, np.reshape(decay, (-1, 1)) if np.ndim(decay) else
                                                      decay, t), q)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        D = np.broadcast_to(np.reshape(decay, (-1,)) if np.ndim(decay) else decay, (J,))
        past = t[:, None] >= D[None, :]  # (n, J): the offset is over
        assert np.array_equal(got[past], q[past])
        assert np.array_equal(got[:, 4], q[:, 4])
        parts = [apply_quintic_rotation_offsets(x0, v0, a0, decay, t[a:b], q[a:b]) for a, b in ((0, 1), (1, 9), (9, 30))]
        assert np.array_equal(np.concatenate(parts), got)
    with pytest.raises(ParameterError, match=rf"v0: expected \({J}, 3\); got \({J - 1}, 3\)"):
        apply_quintic_rotation_offsets(x0, v0[1:], a0, 0.5, t, q)
    with pytest.raises(ParameterError, match=r"t: expected \(30,\) times"):
        apply_quintic_rotation_offsets(x0, v0, a0, 0.5, t[1:], q)


def _random_quats(rng, shape):
    return R.normalize(rng.normal(size=shape + (4,)))


def test_the_assembly_kernels_in_cpp_give_the_bits_of_numpy(scott_db):
    """csrc/assembly.cpp's placement and pulls, and the helpers that replaced numpy calls on a live step's path,
    against the numpy they replaced: the same bits (their operations in their order), zeros and identities
    included (the sign of a zero decides an angle of pi)."""

    import gesturedb._core as _core
    from gesturedb.motion import forward_kinematics
    from gesturedb.synth import assemble as A
    from gesturedb.synth.contacts import _planar_distance

    rng = np.random.default_rng(5)
    J = scott_db.skeleton.n_joints
    q = _random_quats(rng, (40,))
    q[:3] = [[1, 0, 0, 0], [0, 0, 1, 0], [-1, 0, 0, 0]]  # identity, half a turn about y, -identity
    fwd = R.apply(q, np.broadcast_to(np.array([0.0, 0.0, 1.0]), (40, 3)))
    assert np.array_equal(A._yaw_of(q), np.arctan2(fwd[:, 0], fwd[:, 2]))
    a = rng.normal(size=(500, 3)) * rng.uniform(1e-3, 1e3, size=(500, 1))
    assert np.array_equal(R.norm3(a), np.linalg.norm(a, axis=-1, keepdims=True))
    assert all(_planar_distance(u, v) == np.linalg.norm((u - v)[[0, 2]]) for u, v in zip(a[:250], a[250:]))
    # placement: a piece turned and moved onto the output (_place) and recordings put at the origin (placed_frames)
    rot, root = _random_quats(rng, (9, J)), rng.normal(size=(9, 3))
    rot[0, 0] = [1, 0, 0, 0]
    for theta in (0.0, 0.7, -np.pi, np.pi):
        yq = A._yaw_quat(theta)
        src, dst = rng.normal(size=3), rng.normal(size=3)
        want_rot = rot.copy()
        want_rot[:, 0] = R.multiply(np.broadcast_to(yq, (9, 4)), rot[:, 0])
        d = root - src
        d[:, 1] = 0.0
        want_root = R.apply(np.broadcast_to(yq, (9, 4)), d) + dst
        want_root[:, 1] = root[:, 1]
        got_rot, got_root = A._place(rot, root, (theta, src, dst))
        assert np.array_equal(got_rot, want_rot) and np.array_equal(got_root, want_root)
    yq, centre = A._yaw_quat(rng.uniform(-np.pi, np.pi, size=9)), rng.normal(size=(9, 3))
    want_root = R.apply(yq, root - centre)
    want_root[:, 1] = root[:, 1]
    want_rot = rot.copy()
    want_rot[:, 0] = R.multiply(yq, rot[:, 0])
    got_rot, got_root = _core.place_frames(yq, rot, root, centre, None, False)
    assert np.array_equal(got_rot, want_rot) and np.array_equal(got_root, want_root)
    # the pulls' loop over frames
    yaw, xz = rng.uniform(-4, 4, size=12), rng.normal(size=(12, 2))
    for first, h_prev, y_prev in ((1, yaw[0], xz[0]), (0, 3.1, np.array([0.2, -0.4]))):
        dyaw = A._wrap(np.diff(yaw) if first else np.diff(np.concatenate([[2.9], yaw])))
        dx = np.diff(xz, axis=0) if first else np.diff(np.concatenate([[[0.1, 0.1]], xz]), axis=0)
        h, y = np.empty(12), np.empty((12, 2))
        h[0], y[0] = yaw[0], xz[0]
        hp, yp = h_prev, y_prev
        for t in range(first, 12):  # the numpy loop _Pull.run ran until 2026-11-28
            i = t - 1 + (1 - first)
            h[t] = hp + dyaw[i] - 0.03 * A._wrap(hp)
            c, s = np.cos(h[t] - yaw[t]), np.sin(h[t] - yaw[t])
            y[t] = yp + np.array([c * dx[i, 0] + s * dx[i, 1], -s * dx[i, 0] + c * dx[i, 1]]) - 0.01 * yp
            hp, yp = h[t], y[t]
        gh, gy = _core.pull_root(yaw, np.ascontiguousarray(dyaw), dx, first, 0.03, 0.01, float(h_prev),
                                 float(y_prev[0]), float(y_prev[1]))
        assert np.array_equal(gh[first:], h[first:]) and np.array_equal(gy[first:], y[first:])
    # forward kinematics without a Motion: a Motion's, rotations renormalised alike
    drift = rot * (1 + 1e-9)
    m = Motion(skeleton=scott_db.skeleton, fps=15.0, rotations=drift, root_positions=root)
    for got, want in zip(forward_kinematics(scott_db.skeleton, drift, root), m.forward_kinematics()):
        assert np.array_equal(got, want)


def test_a_seams_offset_in_cpp_equals_the_numpy_reference(scott_db):
    """csrc/assembly.cpp's seam offset against _seam_arithmetic_numpy: equal to rounding (atan2 is libm's there,
    numpy's rounds differently in the last bit for some values), with the samples' branches through pi, with
    and without the adaptive decays, and the root's quintic in C++ against root + quintic_offsets."""
    import gesturedb._core as _core
    from gesturedb.synth import assemble as A
    from gesturedb.synth.seams import quintic_offsets

    rng = np.random.default_rng(6)
    J = scott_db.skeleton.n_joints
    new = _random_quats(rng, (3, J))
    turn = rng.normal(size=(J, 3))
    turn /= np.linalg.norm(turn, axis=-1, keepdims=True)
    ang = rng.uniform(0, np.pi, size=(J, 1))
    ang[:4] = np.pi - 0.02  # offsets that pass through pi over the three samples
    old = np.stack([R.multiply(R.from_axis_angle(turn * (ang + 0.02 * k)), new[k]) for k in range(3)])
    old_root, new_root = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    accel = (rng.uniform(1, 400, size=J), 3.0)
    for acc in (accel, None):
        got = _core.seam_offset(old, new, old_root, new_root, 15.0, None if acc is None else acc[0],
                                0.0 if acc is None else acc[1], 8 / 15, 3 * 8 / 15)
        want = A._seam_arithmetic_numpy(old, new, old_root, new_root, fps=15.0, decay_s=8 / 15, accel=acc)
        np.testing.assert_allclose(got[0], np.stack(want[0]), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(got[1], np.stack(want[1]), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(got[2], want[2], rtol=1e-12)
        assert got[3] == pytest.approx(want[3], rel=1e-12)
    assert np.abs(got[0][1][:4]).max() < 2  # through pi: the velocity of 0.02 rad a frame, not a 2 pi jump
    x0, v0, a0 = rng.normal(size=(3, 3))
    t, base = np.arange(12) / 15.0, rng.normal(size=(12, 3))
    np.testing.assert_allclose(_core.add_quintic_offsets(x0, v0, a0, 0.5, t, base),
                               base + quintic_offsets(x0, v0, a0, 0.5, t), rtol=0, atol=1e-14)
    assert np.array_equal(_core.add_quintic_offsets(x0, v0, a0, 0.5, t, base)[t >= 0.5], base[t >= 0.5])
    with pytest.raises(ValueError, match=r"new_rot: expected \(3, \d+, 4\); got \(2, "):
        _core.seam_offset(old, new[:2], old_root, new_root, 15.0, None, 0.0, 0.5, 1.5)


@pytest.mark.slow
def test_no_heading_drift_over_five_minutes(scott_db, scott_dir):
    """The four input WAVs (and the first again) end to end: 5 minutes keep facing forward, near the origin."""
    wavs = sorted((scott_dir / "inputs").glob("*.wav"))
    parts = [sf.read(str(w), dtype="float32")[0] for w in wavs]
    sr = sf.info(str(wavs[0])).samplerate
    audio = np.concatenate(parts + parts[:1])[: 300 * sr]
    assert audio.shape[0] >= 299 * sr
    res = Searcher(scott_db).synthesize(audio, sr=sr)
    keys = {k: j for j, k in __import__("gesturedb.io.joints", fromlist=["body_keys"]).body_keys(
        scott_db.joint_names).items()}
    h = P.heading_deg(res.positions, left_hip=keys["left_upleg"], right_hip=keys["right_upleg"])
    minute = int(60 * scott_db.fps)
    for a in range(0, h.shape[0] - minute + 1, minute):  # every minute's mean heading within 20 degrees
        r = np.radians(h[a:a + minute])
        assert abs(np.degrees(np.arctan2(np.sin(r).mean(), np.cos(r).mean()))) < 20, a
    db_xz = np.asarray(scott_db.root_positions[:, [0, 2]], dtype=np.float64)
    reach = np.linalg.norm(db_xz - db_xz.mean(0), axis=1).max()
    assert np.linalg.norm(res.motion.root_positions[:, [0, 2]], axis=1).max() < reach + 0.5
