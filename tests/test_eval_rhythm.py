"""The evaluation's rhythm agreement (gesturedb.eval.rhythm): the paper's Hamming distance and the one beyond chance."""
from __future__ import annotations

import numpy as np
import pytest

from gesturedb.errors import ParameterError
from gesturedb.eval.rhythm import rhythm_agreement, rhythm_hamming, rhythm_signatures, seam_minima
from gesturedb.features.rhythm import (
    audio_rhythm,
    hamming,
    hamming_beyond_chance,
    hand_speed,
    motion_rhythm,
    speed_minima,
)

FPS = 15.0
T = 128  # one clip (no pause between the words) of 32 bins of 4 frames
JOINTS = {"root": 0, "left_hip": 1, "right_hip": 2, "left_shoulder": 3, "right_shoulder": 4,
          "left_wrist": 5, "right_wrist": 6}
WORD_BINS = np.arange(0, 32, 4)  # 8 speech bits
# eight times the calm motion's minima: six of the eight words marked (not 0 and 28), ten off them
BUSY = [4, 8, 12, 16, 20, 24, 1, 2, 6, 9, 10, 13, 14, 18, 22, 26]


def _bits(sig) -> list[int]:
    return [i for i in range(32) if (int(sig) >> i) & 1]


def _motion(dip_bins) -> np.ndarray:
    """A still body whose left wrist circles at 0.6 m/s and slows to 0.1 m/s in the middle of each bin of
    ``dip_bins`` (frame 4 b + 2): a prominent hand-speed minimum there and nowhere else."""
    t = np.arange(T, dtype=np.float64)
    speed = np.full(T, 0.6)
    for b in dip_bins:
        speed -= 0.5 * np.exp(-0.5 * (t - (4 * b + 2)) ** 2)
    radius = 0.2
    angle = np.cumsum(speed) / FPS / radius
    pos = np.zeros((T, 7, 3))
    pos[:, :5] = [[0, 1.0, 0], [0.1, 0.95, 0], [-0.1, 0.95, 0], [0.2, 1.5, 0], [-0.2, 1.5, 0]]
    pos[:, 5] = np.stack([0.3 + radius * np.cos(angle), 1.2 + radius * np.sin(angle), np.full(T, 0.3)], axis=1)
    pos[:, 6] = [-0.3, 1.1, 0.2]
    return pos


def _words():
    start = (4 * WORD_BINS + 1.5) / FPS  # inside each bin, away from its edges
    return start, np.append(start[1:], T / FPS)  # no pause: one clip over the whole motion


def test_beyond_chance_is_the_features_function_on_the_same_signatures_where_the_plain_distance_disagrees():
    ws, we = _words()
    calm = _motion([6, 22])  # two minima, both off the words
    busy = _motion(BUSY)
    speech = audio_rhythm(ws, start_s=0.0, end_s=T / FPS)
    assert _bits(speech) == list(WORD_BINS)
    got = {}
    for name, pos in (("calm", calm), ("busy", busy)):
        # the signatures by hand, from the features module, on the one clip [0, T)
        motion = motion_rhythm(hand_speed(pos, joints=JOINTS, fps=FPS), start=0, length=T, fps=FPS)
        sp, mo = rhythm_signatures(pos, word_start_s=ws, word_end_s=we, fps=FPS, joints=JOINTS)
        assert sp.tolist() == [speech] and mo.tolist() == [motion]
        r = rhythm_agreement(pos, word_start_s=ws, word_end_s=we, fps=FPS, joints=JOINTS)
        assert r["rhythm_hamming"] == float(hamming(speech, motion))
        assert r["rhythm_beyond_chance"] == pytest.approx(float(hamming_beyond_chance(speech, motion)))
        assert r["rhythm_hamming"] == rhythm_hamming(pos, word_start_s=ws, word_end_s=we, fps=FPS, joints=JOINTS)
        got[name] = (_bits(motion), r)
    assert got["calm"][0] == [6, 22]
    assert got["busy"][0] == sorted(BUSY)
    calm_r, busy_r = got["calm"][1], got["busy"][1]
    # the paper's distance prefers the calm motion, whose two minima both miss (8 unmarked words + 2 = 10
    # against 2 + 10 = 12); beyond chance prefers the busy one, which marks six of the eight words
    # (H - (n_a - n_b)(1 - 2 n_a / 32): 10 + 6 / 2 = 13 against 12 - 8 / 2 = 8)
    assert (calm_r["rhythm_hamming"], busy_r["rhythm_hamming"]) == (10.0, 12.0)
    assert (calm_r["rhythm_beyond_chance"], busy_r["rhythm_beyond_chance"]) == pytest.approx((13.0, 8.0))


def test_motion_with_as_many_minima_as_words_scores_the_same_both_ways():
    ws, we = _words()
    pos = _motion([4, 8, 12, 16, 2, 6, 10, 14])  # 8 bits, 4 on words
    r = rhythm_agreement(pos, word_start_s=ws, word_end_s=we, fps=FPS, joints=JOINTS)
    assert r["rhythm_hamming"] == r["rhythm_beyond_chance"] == 8.0


def test_pauses_at_the_seams_against_inside_the_windows():
    """Windows of 8 frames whose cuts fall before frames 10, 18, .., 114: at 15 fps the two frames beside
    each cut are "at the seam" (28 of the 128). A hand that slows at four cuts and three times inside
    pauses 4 / 28 times a seam frame against 3 / 100 inside (ratio 4.8); one that slows only inside, 0."""
    cuts = np.arange(10, 120, 8)
    seam_frames = np.sort(np.concatenate([cuts - 1, cuts]))
    at_cuts = [2, 10, 18, 26]  # dips at frames 4 b + 2 = 10, 42, 74, 106: a cut's first frame
    inside = [5, 13, 21]  # frames 22, 54, 86: 3.5 frames or more from a cut
    for dips, want_seam, want_inside in ((at_cuts + inside, 4, 3), (list(range(1, 31, 4)), 0, 8)):
        pos = _motion(dips)
        mins = speed_minima(hand_speed(pos, joints=JOINTS, fps=FPS), fps=FPS)
        # the minima are where the hand slows, to a frame (the velocity is a difference of two frames)
        assert len(mins) == len(dips) and np.abs(mins - np.sort(4 * np.array(dips) + 2)).max() <= 1
        assert np.isin(mins, seam_frames).sum() == want_seam
        r = seam_minima(pos, fps=FPS, joints=JOINTS, boundaries=cuts)
        assert r["seam_rate"] == pytest.approx(want_seam / 28) and r["inside_rate"] == pytest.approx(want_inside / 100)
        assert r["ratio"] == pytest.approx((want_seam / 28) / (want_inside / 100))
    # at 30 fps the seam is the same time: two frames on each side of the cut
    pos30 = np.repeat(_motion(inside), 2, axis=0)
    r30 = seam_minima(pos30, fps=2 * FPS, joints=JOINTS, boundaries=2 * cuts)
    assert r30["seam_rate"] == 0.0 and r30["inside_rate"] > 0
    with pytest.raises(ParameterError, match=r"boundaries: expected frame indices in \[1, 127\] for 128 frames"):
        seam_minima(_motion(inside), fps=FPS, joints=JOINTS, boundaries=[0, 8])
