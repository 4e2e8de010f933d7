"""GENEA- and BEAT/EMAGE-convention metrics on hand-made signals with known values."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.eval import conventions as C
from gesturedb.eval import metrics as M


def _x_of_speed(speed_m_s: np.ndarray, fps: float) -> np.ndarray:
    """One joint moving along x with the given per-step speeds: (len + 1, 1, 3) metres."""
    pos = np.zeros((speed_m_s.size + 1, 1, 3))
    pos[1:, 0, 0] = np.cumsum(speed_m_s) / fps
    return pos


@pytest.mark.parametrize("fps", [15.0, 30.0])
def test_genea_speed_histogram_is_in_cm_s_at_the_data_frame_rate_and_drops_the_overflow(fps):
    speed = np.r_[np.full(20, 0.205), np.full(10, 0.705)]  # 20.5 cm/s and 70.5 cm/s (beyond 50)
    pos = _x_of_speed(speed, fps)
    counts, edges = C.genea_histogram(pos, fps=fps)
    assert edges[-1] == C.GENEA_SPEED_MAX_CM_S and edges[1] - edges[0] == 1.0
    assert counts.sum() == 20 and counts[20] == 20  # the fast third is dropped, not clipped
    ours, _ = M.speed_histogram(pos, fps=fps)  # our convention keeps it (clipped into the last bin)
    assert ours.sum() == 30


def test_genea_acceleration_histogram_of_a_constant_acceleration():
    fps, a = 30.0, 1.505  # m/s^2 -> 150.5 cm/s^2, mid-bin
    t = np.arange(40) / fps
    pos = np.zeros((40, 2, 3))
    pos[:, 0, 2] = 0.5 * a * t ** 2
    pos[:, 1, 1] = 0.5 * a * t ** 2  # second joint, other axis: same magnitude
    counts, edges = C.genea_histogram(pos, fps=fps, kind="acceleration")
    assert counts.sum() == 2 * 38 and counts[150] == 2 * 38
    assert edges[-1] == C.GENEA_ACCEL_MAX_CM_S2


def test_genea_hellinger_conventions_differ_where_speeds_overflow():
    fps = 15.0
    slow = _x_of_speed(np.full(30, 0.105), fps)
    mixed = _x_of_speed(np.r_[np.full(15, 0.105), np.full(15, 1.5)], fps)
    # GENEA drops the fast half: what remains is identical to the slow motion
    assert C.genea_hellinger(mixed, slow, fps=fps) == pytest.approx(0.0, abs=1e-12)
    # ours counts it: half the mass in another bin -> H = sqrt(1 - sqrt(1/2))
    assert M.speed_hellinger(mixed, slow, fps=fps) == pytest.approx(np.sqrt(1 - np.sqrt(0.5)))
    assert C.genea_hellinger(slow, _x_of_speed(np.full(30, 0.305), fps), fps=fps) == pytest.approx(1.0)
    assert np.isnan(C.genea_hellinger(_x_of_speed(np.full(30, 1.5), fps), slow, fps=fps))


def test_genea_histogram_rejects_bad_input():
    with pytest.raises(ParameterError, match="kind: expected 'speed' or 'acceleration'; got 'jerk'"):
        C.genea_histogram(np.zeros((5, 1, 3)), fps=15.0, kind="jerk")
    with pytest.raises(ParameterError, match=r"positions: expected \(F, J, 3\)"):
        C.genea_histogram(np.zeros((5, 3)), fps=15.0)


def _pulsing(fps: float, duration_s: float, period_s: float, depth: float):
    """Speed 1 - depth * cos(2 pi t / period): minima of speed 1 - depth at multiples of the period, mean 1 m/s."""
    t = np.arange(int(duration_s * fps)) / fps
    pos = np.zeros((t.size, 1, 3))
    pos[:, 0, 0] = t - depth * period_s / (2 * np.pi) * np.sin(2 * np.pi * t / period_s)
    return pos, np.arange(1, int(duration_s / period_s)) * period_s


def test_beat_align_headline_threshold_comes_from_the_reference_speed():
    fps = 30.0
    pos, beats = _pulsing(fps, 6.0, 0.5, depth=0.9)  # minima at 0.1 m/s, mean 1 m/s
    # the clip's own threshold (0.3 x 1 m/s) drops every minimum: no motion beat, nothing to match
    assert M.beat_align(pos, fps=fps, joints=[0], audio_beats_s=beats, direction="audio_to_motion") == 0.0
    # a calmer database (mean 0.2 m/s -> threshold 0.06 m/s) keeps them; audio beats sit on them
    assert C.beat_align_headline(pos, fps=fps, joints=[0], audio_beats_s=beats,
                                 reference_speed_m_s=0.2) == pytest.approx(1.0, abs=1e-6)
    # audio beats half a period off the strokes: exp(-0.25^2 / (2 * 0.3^2)) each
    off = beats[:-1] + 0.25
    assert C.beat_align_headline(pos, fps=fps, joints=[0], audio_beats_s=off, reference_speed_m_s=0.2) == \
        pytest.approx(np.exp(-0.25 ** 2 / (2 * 0.3 ** 2)), abs=1e-6)


def test_reference_mean_speed_matches_the_motion_beats_speed():
    fps = 30.0
    pos, _ = _pulsing(fps, 6.0, 0.5, depth=0.5)
    ref = C.reference_mean_speed(pos, fps=fps, joints=[0])
    assert ref.shape == (1,) and ref[0] == pytest.approx(1.0, rel=0.01)
    # with the clip's own mean as the reference, the headline equals beat_align(audio_to_motion)
    beats = np.arange(1, 11) * 0.5 + 0.1
    assert C.beat_align_headline(pos, fps=fps, joints=[0], audio_beats_s=beats, reference_speed_m_s=ref) == \
        pytest.approx(M.beat_align(pos, fps=fps, joints=[0], audio_beats_s=beats, direction="audio_to_motion"))


def test_convention_metrics_rows_compare_with_the_ground_truth():
    fps = 30.0
    gt, beats = _pulsing(fps, 6.0, 0.5, depth=0.9)
    fast = gt * 3.0  # three times the speed: beyond GENEA's last speed edge for most frames
    rows = C.convention_metrics({"ground_truth": gt, "fast": fast}, fps=fps, joints=[0], audio_beats_s=beats,
                                reference_speed_m_s=0.2)
    assert set(rows["fast"]) == {k for k, _, _ in C.CONVENTION_COLUMNS}
    assert rows["ground_truth"]["genea_hellinger_speed_gt"] == 0.0
    assert rows["fast"]["genea_hellinger_speed_gt"] == pytest.approx(C.genea_hellinger(fast, gt, fps=fps, joints=[0]))
    assert rows["ground_truth"]["beat_align_headline"] == pytest.approx(1.0, abs=1e-6)
    assert np.isnan(rows["fast"]["genea_hellinger_speed_db"])  # no database counts given
