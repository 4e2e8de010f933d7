"""Self-trained FGD (gesturedb/eval/fgd.py): the distance on hand-made Gaussians, the encoder on real motion."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

import gesturedb  # noqa: E402
from gesturedb.errors import ParameterError  # noqa: E402
from gesturedb.eval.common import feature_joint_indices, metric_positions, upper_body_joints  # noqa: E402
from gesturedb.eval.fgd import SelfFGD, frechet_distance, motion_windows  # noqa: E402


def test_frechet_distance_matches_the_closed_form_for_diagonal_gaussians():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4000, 3)) * [1.0, 2.0, 0.5] + [0.0, 1.0, 0.0]
    b = rng.normal(size=(5000, 3)) * [1.0, 1.0, 1.5] + [0.5, 0.0, 0.0]
    ca, cb = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    # the formula on the samples' own moments, by hand for (nearly) diagonal covariances
    want = np.sum((a.mean(0) - b.mean(0)) ** 2) + np.sum((np.sqrt(np.diag(ca)) - np.sqrt(np.diag(cb))) ** 2)
    assert frechet_distance(a, b) == pytest.approx(want, rel=0.02)
    assert frechet_distance(a, b) == pytest.approx(frechet_distance(b, a), rel=1e-6)
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ParameterError, match=r"codes: expected two arrays \(n >= 2, L\) with the same L"):
        frechet_distance(a, b[:, :2])


def test_motion_windows_stack_positions_and_velocities():
    T, J = 40, 3
    pos = np.cumsum(np.ones((T, J, 3)), axis=0) * 0.1  # every coordinate moves 0.1 per frame
    w = motion_windows(pos, joints=[0, 2], window=32, fps=15.0, stride=4)
    assert w.shape == (3, 32, 12) and w.dtype == np.float32
    np.testing.assert_allclose(w[1, 0, :6], pos[4, [0, 2]].ravel(), rtol=1e-6)
    np.testing.assert_allclose(w[..., 6:], 1.5, rtol=1e-5)  # 0.1 m per frame at 15 fps
    assert motion_windows(pos[:10], joints=[0], window=32, fps=15.0).shape == (0, 32, 6)


@pytest.fixture(scope="module")
def fgd_setup(scott_db_path):
    with gesturedb.open(scott_db_path) as db:
        fj = feature_joint_indices(db)
        root = fj["root"]
        joints = upper_body_joints(db.skeleton.parents, root=root, hips=[fj["left_hip"], fj["right_hip"]])
        f = SelfFGD.try_build(db, joints=joints, root=root)
        rec = db.recordings[0]
        pos = metric_positions(db.joint_positions[rec.start_frame:rec.stop_frame], root)
        again = SelfFGD.try_build(db, joints=joints, root=root)
        return f, pos, again


def test_self_fgd_is_zero_on_the_database_and_large_on_a_frozen_pose(fgd_setup):
    f, pos, again = fgd_setup
    assert again is f  # trained once per database and process
    assert f.db_codes.shape[1] == 16 and np.allclose(f.db_codes.std(0), 1.0)
    whole = frechet_distance(f.codes(pos), f.db_codes)  # the database is this recording (no mirror)
    assert whole < 0.05
    rng = np.random.default_rng(1)
    stretches = [frechet_distance(f.codes(pos[s:s + 232]), f.db_codes) for s in rng.integers(0, pos.shape[0] - 232, 4)]
    still = frechet_distance(f.codes(np.repeat(pos[:1], 232, axis=0)), f.db_codes)
    assert still > 3 * max(stretches)
    # deterministic for a seed
    np.testing.assert_allclose(f.codes(pos[:100]), f.codes(pos[:100]))
