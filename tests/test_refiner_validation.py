"""The refiner's validation (issue 40): the split, the best checkpoint, the verdict and what
synth does with it, the training recipe's parts, and the device a run trains on."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the refiner extra (torch==2.13.0) is not installed: "
                                           "pip install '.[refiner]'")

import gesturedb  # noqa: E402
from gesturedb.errors import ParameterError  # noqa: E402
from gesturedb.refiner import data as D  # noqa: E402
from gesturedb.refiner import validation as V  # noqa: E402
from gesturedb.refiner.model import Generator, augment, band_change, band_powers, high_band_energy  # noqa: E402
from gesturedb.refiner.representation import moving_joints  # noqa: E402
from gesturedb.refiner.train import Refiner, TrainConfig, Trainer, read_checkpoint, resolve_device  # noqa: E402

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU that torch sees")


@pytest.fixture(scope="module")
def mirrored_db_path(scott_dir, tmp_path_factory):
    """The real recording and its mirrored copy: the split must hold back the same stretch of both."""
    out = tmp_path_factory.mktemp("mirrored") / "scott_m.h5"
    gesturedb.build([scott_dir], out, mirror=True).close()
    return out


# -- the split ------------------------------------------------------------------------------
def test_validation_never_shares_frames_with_training_windows(mirrored_db_path):
    with gesturedb.open(mirrored_db_path) as db:
        recs = db.recordings
        assert len(recs) == 2 and recs[1].name == recs[0].name + "~mirror"
        starts = D.window_starts(db, stride=3)
        starts = starts[D.usable_windows(db, starts, 0.25)]
        val = D.split_windows(db, starts, 0.25)
        assert 0 < val.sum() < len(val)
        first = np.array([r.start_frame for r in recs])
        rec = np.asarray(db.frame_recording[starts])
        within = starts - first[rec]  # the frame within its recording: the same instant in source and mirror
        train_frames = {int(a) + t for a in within[~val] for t in range(64)}
        val_frames = {int(a) + t for a in within[val] for t in range(64)}
        assert not train_frames & val_frames  # nor reflected: a mirror's frame i is its source's frame i
        cut = D.held_out_from(db, 0.25)
        assert cut[0] == cut[1] == int(np.floor(recs[0].n_frames * 0.75))
        assert max(train_frames) < cut[0] <= min(val_frames)
        # the training windows' fakes may copy no segment reaching into a held-out stretch, of either copy
        ex = D.exclusion(db, starts, held_out=cut, val=val)
        seg = db.chunks
        seg_rec = np.asarray(seg.recording)
        reaches = np.asarray(seg.start) + np.asarray(seg.length) - first[seg_rec] > cut[seg_rec]
        assert reaches.any() and ex[~val][:, reaches].all()
        assert not ex[val][:, reaches].all()  # validation windows search as synthesis does
        assert not ex[~val].all(axis=1).any()  # every training window has something left to copy


def test_a_split_that_leaves_no_side_is_refused(scott_db):
    with pytest.raises(ParameterError, match=r"val_fraction: 0.01 leaves \d+ training and 0 validation windows"):
        D.make_training_data(scott_db, stride=50, val_fraction=0.01)
    with pytest.raises(ParameterError, match=r"val_fraction: expected a fraction in \[0, 1\), got 1.5"):
        D.held_out_from(scott_db, 1.5)


def test_the_validation_measures_bands_and_speeds_as_eval_does():
    # one home for the definitions (gesturedb.measures): the validator's band power of windows is the
    # stroke tables' band power of those windows pooled as recordings, its speed histogram eval's
    from gesturedb.eval import metrics as M
    from gesturedb.eval import strokes

    rng = np.random.default_rng(4)
    fps = 15.0
    pos = np.cumsum(rng.standard_normal((3, 64, 4, 3)) * 0.01, axis=1)
    pos[:, :, 0] = 0.0  # the validator's windows are root-relative already
    arms = [1, 3]
    bands = V._arm_bands(np.diff(pos[:, :, arms], axis=1) * fps, fps)
    pooled = strokes.pooled_band_power(list(pos), fps=fps, joints=arms)
    assert list(pooled) == [strokes.band_key(b) for b in strokes.BANDS_HZ]
    np.testing.assert_allclose(bands, list(pooled.values()), rtol=1e-12)
    one = strokes.band_power(pos[0], fps=fps, joints=arms)
    np.testing.assert_allclose(V._arm_bands(np.diff(pos[:1, :, arms], axis=1) * fps, fps), list(one.values()),
                               rtol=1e-12)
    hist = V._speed_hist(pos[:1], fps)
    counts, _ = M.speed_histogram(pos[0], fps=fps)
    assert np.array_equal(hist, counts)


# -- the best checkpoint and the verdict ----------------------------------------------------------
class _Scripted:
    """A validator whose scores are given: identity 1.0, then ``scores`` in turn."""

    def __init__(self, data, scores, identity=1.0):
        idx = np.arange(2)
        self.audio, self.knn, self.real = data.audio(idx), data.fake(idx), data.real(idx)
        self.n, self.scores = 2, list(scores)
        self.capture = {"jerk": 40.0}
        self.identity = self._m(identity)

    @staticmethod
    def _m(score):
        return {"score": score, "jerk": 1.0, "band": [1.0, 1.0, 1.0], "hellinger": 0.0, "critic_gap": 0.0, "hf": 0.0,
                "hellinger_db": 0.0, "band_db": 0.0, "fgd_db": 0.0}  # every metric a Validator measures, the guards' included

    def measure(self, channels, *, critic_gap=float("nan")):
        return self._m(self.scores.pop(0))


def _tiny(seed=0, W=6, T=16):
    rng = np.random.default_rng(seed)
    F = 3 * W + T
    return D.TrainingData(frame_audio=rng.standard_normal((F, 28)).astype(np.float32),
                          frame_real=rng.standard_normal((F, 12)).astype(np.float32),
                          knn=rng.standard_normal((W, 12, T)).astype(np.float32), joints=np.arange(1, 3),
                          starts=3 * np.arange(W), ks=np.ones(W, np.int64))


_FEATURES = {"joint_names": ["root", "spine", "head"], "parents": [-1, 0, 1], "fps": 15.0, "audio_channels": 28,
             "n_mfcc": 13}
_CFG = dict(batch=3, width=8, n_critic=1, seed=3, w1=0.0)  # w1 0: every step changes the generator


@pytest.mark.parametrize("scores, best, beats", [
    ([1.2, 0.7, 0.9], 2, True),      # iteration 2 is best and 30 % better than the identity
    ([1.1, 0.99, 1.3], 0, False),    # its best is 1 % better, under the 2 % margin: the identity is kept
    ([1.5, 1.4, 1.6], 0, False),     # worse than the identity all along: the identity is kept
], ids=["better", "within-margin", "worse"])
def test_the_best_generator_by_validation_is_kept_and_applied(scores, best, beats, tmp_path):
    tr = Trainer(_tiny(), TrainConfig(**_CFG), "id", _FEATURES, validator=_Scripted(_tiny(), scores))
    states = {0: {k: v.clone() for k, v in tr.G.state_dict().items()}}  # the untrained generator: the identity
    for _ in scores:
        tr.step()
        tr.validate()
        states[tr.iteration] = {k: v.clone() for k, v in tr.G.state_dict().items()}
    v = tr.verdict()
    assert v["best_iteration"] == best and v["beats_identity"] is beats
    assert v["improvement"] == pytest.approx(1 - min(scores) if best else 0.0)
    assert v.get("identity_kept", False) is (best == 0)
    tr.save(tmp_path / "r.pt")
    ck = read_checkpoint(tmp_path / "r.pt", training=True)
    assert ck["validation"]["verdict"] == v and [r[0] for r in ck["validation"]["log"]] == [1, 2, 3]
    assert ck["validation"]["trained_best"]["iteration"] == 1 + scores.index(min(scores))
    ref = Refiner.load(tmp_path / "r.pt")
    for k, t in ref.G.state_dict().items():  # the best iteration's weights, not the last
        assert torch.equal(t, states[best][k]), k
    assert not all(torch.equal(t, states[3][k]) for k, t in ref.G.state_dict().items())
    kind, message = ref.assess()
    assert kind == ("better" if beats else "worse") and ref.is_identity is (best == 0)
    if best == 0:  # what it applies changes nothing, and the message says so with the closest trained one
        assert ref.is_identity  # refine() returns its input as it is
        motion_like = torch.randn(2, 12, 16)
        with torch.no_grad():
            assert torch.equal(ref.G(torch.randn(2, 28, 16), motion_like), motion_like)
        assert message == (f"{tmp_path / 'r.pt'}: no trained generator beat the unrefined motion on its validation "
                           f"windows (the closest, iteration 2: score {100 * (1 - min(scores)):+.1f}%); the "
                           "checkpoint keeps the identity: refining with it changes nothing")


def test_the_database_guards_measure_against_the_training_windows_capture(scott_db, monkeypatch):
    """With the capture itself as the input, the validator scores 0 against the validation stretch's
    capture; against the database's own motion it measures the training windows' capture, computed
    here independently by forward kinematics of the database's frames."""
    from gesturedb.eval import metrics as M
    from gesturedb.measures import hellinger_distance

    joints = moving_joints(scott_db.local_rotations)
    starts = D.window_starts(scott_db, stride=16)
    starts = starts[D.usable_windows(scott_db, starts, 0.25)]
    val = D.split_windows(scott_db, starts, 0.25)
    audio, real = D.frame_arrays(scott_db, joints)
    data = D.TrainingData(frame_audio=audio, frame_real=real, joints=joints, starts=starts,
                          knn=np.stack([real[s:s + 64].T for s in starts]), ks=np.ones(len(starts), np.int64), val=val)
    v = V.Validator(scott_db, data)
    m = v.identity
    assert m["score"] == pytest.approx(0, abs=1e-9) and m["hellinger"] == 0.0
    pos = scott_db.motion_from_frames(np.arange(len(scott_db.local_rotations))).positions
    pos = pos - pos[:, :1]  # root-relative, as the validator's windows are

    def hist(which):
        return sum(M.speed_histogram(pos[s:s + 64], fps=scott_db.fps, joints=v.upper)[0] for s in starts[which])

    # abs: the validator's positions come back from float32 channels, a speed on a bin edge may move
    assert m["hellinger_db"] == pytest.approx(hellinger_distance(hist(val), hist(~val)), abs=2e-3)
    assert m["hellinger_db"] > 0.05  # the held-back stretch moves unlike the rest of the recording
    assert v.database["hist"].sum() == (~val).sum() * 63 * len(v.upper)  # every training window's speeds
    # FGD* against the database: eval's windows (gesturedb.eval.fgd.motion_windows) of each validation
    # window's capture, in the validator's encoder, against the training windows' codes
    from gesturedb.eval.fgd import motion_windows
    from gesturedb.measures import frechet_distance

    wins = np.concatenate([motion_windows(pos[s:s + 64], joints=v.upper, window=32, fps=scott_db.fps)
                           for s in starts[val]])
    codes = v.encoder.encode(wins) / v.code_std
    assert m["fgd_db"] == pytest.approx(frechet_distance(codes, v.database["codes"]), rel=1e-3)
    assert m["fgd_db"] > 0.1 and len(v.database["codes"]) == (~val).sum() * 9  # 9 stretches of 32 in 64 frames
    monkeypatch.setattr(V, "DATABASE_WINDOWS", 2)  # a large database: a few evenly spread windows stand for it
    assert V.Validator(scott_db, data).database["hist"].sum() == 2 * 63 * len(v.upper)


def test_a_lower_score_that_moves_unlike_the_database_is_not_better(tmp_path):
    """The guards: the run of issue 40 scored 5.7 % below the identity with every term of the score
    better, and H(speed) against the database's motion 22 % worse (held out and on the inputs it was
    worse against the database too). Its verdict is 'not better', and synth's message says on what."""
    identity = {"score": 2.277, "jerk": 2.45, "band": [1.80, 4.73, 4.71], "hellinger": 0.151, "hellinger_db": 0.0735,
                "band_db": 0.454, "fgd_db": 2.218}
    best = {"score": 2.147, "jerk": 2.42, "band": [1.60, 4.14, 4.30], "hellinger": 0.147, "hellinger_db": 0.0897,
            "band_db": 0.342, "fgd_db": 2.218}
    v = V.verdict(identity["score"], best["score"], 1650, identity=identity, best=best)
    assert v["improvement"] == pytest.approx(0.0571, abs=1e-4) and not v["beats_identity"]
    assert v["worse"] == {"hellinger_db": [0.0735, 0.0897]}
    assert V.describe_worse(v["worse"]) == "H(speed) vs the database's motion 0.0735 -> 0.0897 (+22%)"
    within = dict(best, hellinger_db=0.0735 * 1.019)  # worse by less than the 2 % margin: still better
    assert V.verdict(2.277, 2.147, 1650, identity=identity, best=within)["beats_identity"]
    slower = dict(within, jerk=1 / 2.45 / 1.03)  # jerk now too low, by more than it was too high
    assert V.verdict(2.277, 2.147, 1650, identity=identity, best=slower)["worse"].keys() == {"jerk_error"}
    assert V.verdict(2.277, 2.147, 1650)["beats_identity"]  # without metrics: the score alone, as before

    class _Guarded(_Scripted):
        def measure(self, channels, *, critic_gap=float("nan")):
            return dict(best, critic_gap=0.0, hf=0.0)

    tr = Trainer(_tiny(), TrainConfig(**_CFG), "id", _FEATURES, validator=_Guarded(_tiny(), []))
    tr.validator.identity = dict(identity, critic_gap=0.0, hf=0.0)
    tr.step()
    tr.validate()
    v = tr.verdict()  # the identity is kept, and the verdict says why the trained generator was not
    assert v["identity_kept"] and v["best_iteration"] == 0 and not v["beats_identity"]
    assert v["trained"]["iteration"] == 1 and v["trained"]["worse"] == {"hellinger_db": [0.0735, 0.0897]}
    tr.save(tmp_path / "r.pt")
    kind, message = Refiner.load(tmp_path / "r.pt").assess()
    assert kind == "worse" and message.endswith(
        "no trained generator beat the unrefined motion on its validation windows (the closest, iteration 1: score "
        "+5.7%, worse on H(speed) vs the database's motion 0.0735 -> 0.0897 (+22%)); the checkpoint keeps the "
        "identity: refining with it changes nothing")
    from gesturedb.cli.refiner import verdict_screen

    assert "verdict: NOT better than the unrefined motion on validation: no trained generator kept every guard " \
           "with a score 2% lower (the closest, iteration 1: score +5.7%, worse on H(speed) vs the database's motion " \
           "0.0735 -> 0.0897 (+22%)); the checkpoint keeps the identity" in verdict_screen(tr)


@pytest.mark.parametrize("runs, best, beats", [
    ([(0.7, 0.09), (0.9, 0.074), (0.8, 0.09)], 2, True),   # the lowest score that keeps the guards
    ([(0.7, 0.09), (0.6, 0.09)], 0, False),                # none keeps them: the identity is kept
    ([(0.9, 0.074), (0.5, 0.09), (0.85, 0.073)], 3, True),  # a lower score never displaces a guarded best
], ids=["guarded", "none-guarded", "stays-guarded"])
def test_the_best_generator_keeps_the_guards_when_one_does(runs, best, beats):
    class _WithDatabase(_Scripted):
        def __init__(self, data):
            super().__init__(data, [])
            self.identity = dict(self._m(1.0), hellinger_db=0.0735, band_db=0.45)
            self.runs = list(runs)

        def measure(self, channels, *, critic_gap=float("nan")):
            score, h_db = self.runs.pop(0)
            return dict(self._m(score), hellinger_db=h_db, band_db=0.45)

    tr = Trainer(_tiny(), TrainConfig(**_CFG), "id", _FEATURES, validator=_WithDatabase(_tiny()))
    for _ in runs:
        tr.step()
        tr.validate()
    v = tr.verdict()
    assert v["best_iteration"] == best and v["beats_identity"] is beats
    assert not v["worse"]  # what is kept keeps every guard: the identity when no trained generator did
    if best == 0:
        assert v["trained"] == {"iteration": 2, "improvement": pytest.approx(0.4),
                                "worse": {"hellinger_db": [0.0735, 0.09]}}


def _validated(cfg, scores) -> Trainer:
    """A tiny trainer after one step and one validation per scripted score."""
    tr = Trainer(_tiny(), cfg, "id", _FEATURES, validator=_Scripted(_tiny(), scores))
    for _ in scores:
        tr.step()
        tr.validate()
    return tr


def test_resume_keeps_the_validation_log_and_the_best(tmp_path):
    cfg = TrainConfig(**_CFG)
    tr = _validated(cfg, [0.8, 0.9])
    tr.save(tmp_path / "r.pt")
    again = Trainer(_tiny(), cfg, "id", _FEATURES, validator=_Scripted(_tiny(), [0.5]))
    again.restore(read_checkpoint(tmp_path / "r.pt", training=True))
    assert again.best["iteration"] == 1 and len(again.val_log) == 2
    again.step()
    again.validate()
    assert again.verdict()["best_iteration"] == 3 and again.verdict()["best_score"] == 0.5


def _db_checkpoints(db_path, folder, runs) -> None:
    """``folder/NAME.pt`` for each ``(NAME, validation score)`` of ``runs`` (None: trained without
    validation): one iteration on random data of the database's skeleton, so synth accepts them."""
    from gesturedb.refiner.data import database_identity, feature_identity

    with gesturedb.open(db_path) as db:
        joints = moving_joints(db.local_rotations)
        C, F = 6 * len(joints), 64
        rng = np.random.default_rng(0)
        data = D.TrainingData(frame_audio=rng.standard_normal((F, 28)).astype(np.float32),
                              frame_real=rng.standard_normal((F, C)).astype(np.float32),
                              knn=rng.standard_normal((2, C, 32)).astype(np.float32), joints=joints,
                              starts=np.array([0, 16]), ks=np.ones(2, np.int64))
        identity, features = database_identity(db), feature_identity(db)
    for name, score in runs:
        tr = Trainer(data, TrainConfig(batch=2, width=8, n_critic=1), identity, features,
                     validator=None if score is None else _Scripted(data, [score]))
        tr.step()
        tr.validate()
        tr.save(folder / f"{name}.pt")


def _before_the_guards(path) -> None:
    """Rewrite checkpoint ``path`` as one written before the verdict's guards existed: its verdict
    without ``guards`` and ``worse``, its validation metrics without the database's (what the
    1,652-iteration run of issue 40 holds: a verdict 'better' on its score alone)."""
    ck = torch.load(path, weights_only=True)
    val = ck["validation"]
    for m in [val["identity"], val["best"]["metrics"]]:
        m.pop("hellinger_db"), m.pop("band_db"), m.pop("fgd_db")
    val.pop("trained_best")
    val["verdict"].pop("guards"), val["verdict"].pop("worse")
    val["log"] = [row[:-3] for row in val["log"]]
    torch.save(ck, path)


def test_synth_refuses_a_refiner_that_lost_to_the_identity_unless_forced(scott_db_path, scott_dir, tmp_path,
                                                                          capsys):
    from gesturedb.cli.main import main

    wav = scott_dir / "inputs" / "2_scott_0_3_3.wav"
    _db_checkpoints(scott_db_path, tmp_path, [("lost", 1.3), ("won", 0.5)])
    out = tmp_path / "out.bvh"
    capsys.readouterr()
    assert main(["synth", str(scott_db_path), "--audio", str(wav), "-o", str(out), "--refiner",
                 str(tmp_path / "lost.pt")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"gesturedb synth: error: --refiner {tmp_path / 'lost.pt'}: no trained generator beat the "
                          "unrefined motion on its validation windows (the closest, iteration 1: score -30.0%); the "
                          "checkpoint keeps the identity: refining with it changes nothing; --force uses it anyway")
    assert not out.exists()
    assert main(["synth", str(scott_db_path), "--audio", str(wav), "-o", str(out), "--refiner",
                 str(tmp_path / "lost.pt"), "--force"]) == 0
    assert "warning: " in capsys.readouterr().err and out.exists()
    # it keeps the identity: forced, it changes nothing, to the bit
    assert main(["synth", str(scott_db_path), "--audio", str(wav), "-o", str(tmp_path / "plain.bvh")]) == 0
    assert out.read_bytes() == (tmp_path / "plain.bvh").read_bytes()
    out.unlink()
    assert main(["synth", str(scott_db_path), "--audio", str(wav), "-o", str(out), "--refiner",
                 str(tmp_path / "won.pt")]) == 0
    assert "warning" not in capsys.readouterr().err


# -- the recipe's parts --------------------------------------------------------------------------
def test_frozen_leg_channels_get_no_correction():
    G = Generator(18, width=8, frozen=np.arange(6, 12))
    torch.nn.init.normal_(G.out.weight, std=0.1)
    torch.nn.init.normal_(G.out.bias, std=0.1)
    a, x = torch.randn(2, 28, 20), torch.randn(2, 18, 20)
    c = G.eval().correction(a, x)
    assert torch.all(c[:, 6:12] == 0) and torch.all(c[:, :6] != 0)
    assert torch.equal(G(a, x), x + c)


def test_the_high_band_energy_is_parseval_above_the_cut_off():
    fps, T = 15.0, 60
    t = torch.arange(T) / fps
    slow, fast = torch.sin(2 * np.pi * 1.0 * t), 0.5 * torch.sin(2 * np.pi * 5.0 * t)
    x = torch.stack([slow, fast, slow + fast])[None]  # (1, 3, T)
    e = high_band_energy(x, fps, 3.0)[0]
    assert float(e[0]) == pytest.approx(0.0, abs=1e-6)
    assert float(e[1]) == pytest.approx(float((fast ** 2).sum()), rel=1e-5)  # all of it above 3 Hz
    assert float(e[2]) == pytest.approx(float((fast ** 2).sum()), rel=1e-5)


def test_band_powers_split_the_mean_square_by_band():
    """Bands that cover (0, inf) sum to the mean square of the de-meaned signal (Parseval), with an odd
    and an even length; a sinusoid on a frequency bin lies in its own band only (numpy, not torch)."""
    rng = np.random.default_rng(2)
    fps = 15.0
    edges = ((0.0, 0.5), (0.5, 2.0), (2.0, 4.0), (4.0, float("inf")))
    for T in (63, 64):
        x = rng.standard_normal((2, 3, T)) + 5.0
        p = band_powers(torch.from_numpy(x), fps, edges).numpy()
        ms = ((x - x.mean(-1, keepdims=True)) ** 2).mean(-1)
        np.testing.assert_allclose(p.sum(-1), ms, rtol=1e-10)
        # numpy's FFT of the same signals, band by band
        spec = np.abs(np.fft.fft(x - x.mean(-1, keepdims=True), axis=-1)) ** 2 / T ** 2
        f = np.abs(np.fft.fftfreq(T, 1 / fps))
        want = np.stack([spec[..., (f > 0) & (f >= lo) & (f < hi)].sum(-1) for lo, hi in edges], -1)
        np.testing.assert_allclose(p, want, rtol=1e-10)
    t = np.arange(64) / fps
    sine = np.sin(2 * np.pi * (13 * fps / 64) * t)[None, None]  # 3.05 Hz, on bin 13
    np.testing.assert_allclose(band_powers(torch.from_numpy(sine), fps, edges).numpy()[0, 0], [0, 0, 0.5, 0],
                               atol=1e-12)


def test_the_band_term_keeps_each_joints_power_both_ways():
    """0 for the identity and for a posture offset (the mean is no band); damping a joint's motion and
    amplifying it by the same factor cost the same (two-sided), and the term is per joint: halving one
    of two joints costs half of halving both."""
    knn = torch.from_numpy(_tiny(T=64).knn[:4]).double()  # 2 joints, 64 frames: every band has a bin

    def change(out, inp):
        return band_change(out, inp, _FEATURES["fps"])

    mean = knn.mean(-1, keepdim=True)
    assert float(change(knn, knn)) == 0.0
    assert float(change(knn + 0.3, knn)) == pytest.approx(0.0, abs=1e-12)
    damped, louder = mean + 0.5 * (knn - mean), mean + 2.0 * (knn - mean)
    # log 4 but for eps (a thousandth of the band's mean power), which shrinks the ratio a little
    assert float(change(damped, knn)) == pytest.approx(np.log(4), rel=5e-3)
    assert float(change(louder, knn)) == pytest.approx(float(change(damped, knn)), rel=5e-3)
    one = knn.clone()
    one[:, :6] = damped[:, :6]  # joint 1 damped, joint 2 as it was
    assert float(change(one, knn)) == pytest.approx(np.log(4) / 2, rel=5e-3)


def _output_gradient(tr, correction=None):
    """The gradient the generator step sends back from the generator's output (all its terms)."""
    seen = {}
    real = torch.Tensor.backward

    def spy(self, gradient=None, *args, **kw):
        seen["g"] = gradient.clone()
        return real(self, gradient, *args, **kw)

    if correction is not None:
        c = correction.clone().requires_grad_(True)  # a leaf: the step differentiates through it
        tr.G.correction = lambda a, g: c
    torch.Tensor.backward = spy
    try:
        tr.generator_step()
    finally:
        torch.Tensor.backward = real
    return seen["g"]


def test_adding_jitter_costs_and_smoothing_does_not():
    """The jitter term alone (w1 = w2 = 0): a correction that adds energy above 3 Hz gets a gradient
    against it; one that removes some (smoothing, as a refiner should at a seam) gets none."""
    cfg = TrainConfig(batch=3, width=8, n_critic=1, w2=0.0, w1=0.0, w_hf=1.0, w_band=0.0, w_pose=0.0, seed=4)
    data = _tiny(W=3)
    knn = torch.from_numpy(data.fake(np.arange(3)))  # the batch is all three windows, in some order
    smooth = torch.nn.functional.avg_pool1d(knn, 3, 1, 1, count_include_pad=False) - knn
    fps = _FEATURES["fps"]
    assert bool((high_band_energy(knn + smooth, fps, 3.0).sum(1) < high_band_energy(knn, fps, 3.0).sum(1)).all())
    tr = Trainer(data, cfg, "id", _FEATURES)
    order = torch.from_numpy(data.fake(np.arange(3)))
    # the correction must belong to the batch's windows: the batch is drawn first, so use a shape-only noise
    jitter = 0.3 * torch.randn_like(order) * torch.tensor([1.0, -1.0]).repeat(8)[None, None, :16]
    assert float(_output_gradient(tr, jitter).abs().sum()) > 0
    tr = Trainer(data, cfg, "id", _FEATURES)
    assert float(_output_gradient(tr, torch.zeros_like(order)).abs().sum()) == 0


def test_the_l1_gradient_is_in_gradient_units():
    """w1 = 1 gives the L1 term a gradient of norm 1 per window at the output (1/sqrt(B) for the batch's
    mean), the norm the gradient penalty holds the critic's at: w1 is the ratio of the two pulls."""
    tr = Trainer(_tiny(), TrainConfig(batch=4, width=8, n_critic=1, w1=1.0, w2=0.0, w_hf=0.0, w_band=0.0, w_pose=0.0),
                 "id", _FEATURES)
    torch.nn.init.normal_(tr.G.out.weight, std=0.1)  # a correction that is non-zero everywhere
    g = _output_gradient(tr)
    assert float(g.norm()) == pytest.approx(1 / 4 ** 0.5, rel=1e-5)
    assert torch.allclose(g.flatten(1).norm(dim=1), torch.full((4,), 1 / 4), rtol=1e-5)


def test_the_posture_term_is_in_gradient_units_and_moves_only_the_mean():
    """w_pose = 1 alone: a correction with a non-zero mean in every channel gets a gradient of norm 1
    per window (1/sqrt(B) for the batch's mean), as the L1 term in w1's units, and the same at every
    frame of a channel: it pulls the posture offset back, not the motion about it."""
    tr = Trainer(_tiny(), TrainConfig(batch=4, width=8, n_critic=1, w1=0.0, w2=0.0, w_hf=0.0, w_band=0.0, w_pose=1.0),
                 "id", _FEATURES)
    rng = np.random.default_rng(5)
    offset = torch.from_numpy(rng.choice([-1.0, 1.0], (4, 12, 1)) * rng.uniform(0.1, 1.0, (4, 12, 1))).float()
    wiggle = 0.05 * torch.sin(torch.arange(16) * 2 * np.pi / 16)  # zero mean over the window
    g = _output_gradient(tr, offset + wiggle)
    assert float(g.norm()) == pytest.approx(1 / 4 ** 0.5, rel=1e-5)
    assert torch.allclose(g, g[..., :1].expand_as(g))  # constant in time


@pytest.mark.parametrize("crop, warp", [(1.0, 0.0), (0.75, 0.0), (0.75, 0.1)])
def test_augmentation_crops_and_warps_audio_and_gesture_together(crop, warp):
    T = 64
    ramp = torch.arange(T, dtype=torch.float32)
    a = ramp.expand(3, 2, T).clone()
    x = (10 * ramp).expand(3, 5, T).clone().requires_grad_(True)
    a2, x2 = augment(a, x, torch.Generator().manual_seed(0), crop=crop, warp=warp)
    L = int(round(crop * T))
    assert a2.shape == (3, 2, L) and x2.shape == (3, 5, L)
    assert torch.allclose(x2, 10 * a2[:, :1].expand(-1, 5, -1), atol=1e-4)  # the same resampling of both
    step = a2[:, 0, 1:] - a2[:, 0, :-1]  # a ramp resampled: a constant step per sequence
    assert torch.allclose(step, step[:, :1].expand_as(step), atol=1e-4)
    if crop == 1.0 and warp == 0:
        assert torch.equal(x2, x)
    lo, hi = ((L * (1 - warp) - 1) / (L - 1), (L * (1 + warp) - 1) / (L - 1)) if warp else (1.0, 1.0)
    assert float(step.min()) >= lo - 1e-4 and float(step.max()) <= hi + 1e-4
    x2.sum().backward()  # differentiable: the generator learns through the critic's view
    assert float(x.grad.sum()) == pytest.approx(3 * 5 * L, rel=1e-4)


# -- devices -------------------------------------------------------------------------------------
def test_device_selection(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu" and resolve_device("cpu") == "cpu"
    with pytest.raises(ParameterError, match=r"^device: cuda asked for, but torch sees no CUDA GPU"):
        resolve_device("cuda")
    with pytest.raises(ParameterError, match=r"^device: expected one of auto, cpu, cuda, got 'tpu'"):
        resolve_device("tpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == "cuda"


def test_cli_device_flag_without_a_gpu_is_one_line(scott_db_path, tmp_path, capsys, monkeypatch):
    from gesturedb.cli.main import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["refiner", "train", str(scott_db_path), "-o", str(tmp_path / "r.pt"), "--device", "cuda"]) == 2
    assert "error: device: cuda asked for, but torch sees no CUDA GPU" in capsys.readouterr().err


def _same_weights(a, b):
    return all(torch.equal(t.cpu(), b[k].cpu()) for k, t in a.items())


@CUDA
def test_training_on_cuda_resumes_on_the_cpu_and_applies_there(tmp_path):
    cfg = TrainConfig(**dict(_CFG, w1=0.01))
    gpu = Trainer(_tiny(), cfg, "id", _FEATURES, device="cuda")
    gpu.step()
    gpu.save(tmp_path / "r.pt")
    cpu = Trainer(_tiny(), cfg, "id", _FEATURES, device="cpu")
    cpu.restore(read_checkpoint(tmp_path / "r.pt", training=True))
    assert _same_weights(gpu.G.state_dict(), cpu.G.state_dict())
    cpu.step()  # the optimiser's moments came back on the CPU
    assert cpu.iteration == 2 and next(Refiner.load(tmp_path / "r.pt").G.parameters()).device.type == "cpu"
    back = Trainer(_tiny(), cfg, "id", _FEATURES, device="cuda")
    cpu.save(tmp_path / "r2.pt")
    back.restore(read_checkpoint(tmp_path / "r2.pt", training=True))
    back.step()
    assert back.iteration == 3


def test_a_cpu_checkpoint_restores_on_the_cpu_with_the_sampler_state(tmp_path):
    """Resuming is device-agnostic: the sampler's generator lives on the CPU, so the batches after a
    resume are those of an uninterrupted run (here both on the CPU; on CUDA by the test above)."""
    cfg = TrainConfig(**dict(_CFG, w1=0.01))
    straight = Trainer(_tiny(), cfg, "id", _FEATURES, device="cpu")
    for _ in range(3):
        straight.step()
    first = Trainer(_tiny(), cfg, "id", _FEATURES, device="cpu")
    first.step()
    first.save(tmp_path / "r.pt")
    second = Trainer(_tiny(), cfg, "id", _FEATURES, device="cpu")
    second.restore(read_checkpoint(tmp_path / "r.pt", training=True))
    for _ in range(2):
        second.step()
    assert _same_weights(straight.G.state_dict(), second.G.state_dict())


def test_a_checkpoint_written_on_a_gpu_resumes_and_applies_on_the_cpu(tmp_path, monkeypatch):
    """Without a GPU at hand: a checkpoint whose every storage says ``cuda:0`` (what a run on a GPU
    writes) is mapped to the CPU when read, resumes there and applies there."""
    import torch.serialization as S

    cfg = TrainConfig(**dict(_CFG, w1=0.01))
    tr = Trainer(_tiny(), cfg, "id", _FEATURES, validator=_Scripted(_tiny(), [0.5]))
    tr.step()
    tr.validate()
    with monkeypatch.context() as m:  # tag every storage as a CUDA one while saving
        m.setattr(S, "_package_registry", [(0, lambda storage: "cuda:0", None)] + list(S._package_registry))
        tr.save(tmp_path / "gpu.pt")
    if not torch.cuda.is_available():  # the file does claim CUDA: read as it is, it is refused here
        with pytest.raises(RuntimeError, match="CUDA"):
            torch.load(tmp_path / "gpu.pt", weights_only=True)
    ck = read_checkpoint(tmp_path / "gpu.pt", training=True)  # map_location="cpu"
    assert all(t.device.type == "cpu" for t in ck["generator"].values())
    cpu = Trainer(_tiny(), cfg, "id", _FEATURES, device="cpu", validator=_Scripted(_tiny(), [0.7]))
    cpu.restore(ck, tmp_path / "gpu.pt")
    assert _same_weights(tr.G.state_dict(), cpu.G.state_dict()) and cpu.best["iteration"] == 1
    cpu.step()  # the optimisers' moments came back on the CPU too
    assert cpu.iteration == 2
    ref = Refiner.load(tmp_path / "gpu.pt")
    assert next(ref.G.parameters()).device.type == "cpu" and _same_weights(ref.G.state_dict(), tr.best["generator"])


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity mask on this OS")
def test_training_threads_default_to_the_affinity_mask(scott_db, tmp_path):
    """Under a one-CPU affinity mask (``taskset -c N``) training runs torch on one thread and the
    command line says so, whatever torch's thread count was (here 3; torch's own default counts the
    machine's cores)."""
    from test_refiner import _SMALL, _cache

    _cache(scott_db, tmp_path / "r.pt.data.h5")
    cpu = min(os.sched_getaffinity(0))
    code = f"""
import os, sys
os.sched_setaffinity(0, {{{cpu}}})
import torch
import gesturedb
from gesturedb.cli.main import main
from gesturedb.refiner import train as T
from gesturedb.refiner.train import TrainConfig
seen = []
step = T.Trainer.step
torch.set_num_threads(3)  # what torch might take from the machine's cores: train() must not keep it
T.Trainer.step = lambda self: (seen.append(torch.get_num_threads()), step(self))[1]
with gesturedb.open({str(scott_db.path)!r}) as db:
    T.train(db, {str(tmp_path / "r.pt")!r}, config=TrainConfig(**{_SMALL!r}))
print(seen)
main(["refiner", "train", "--help"])
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[0] == "[1]"
    assert "the CPUs this process may use, 1)" in " ".join(res.stdout.split())


@pytest.mark.parametrize("kind", ["before-guards", "no-validation"])
def test_synth_refuses_a_refiner_without_a_whole_verdict_unless_forced(kind, scott_db_path, scott_dir, tmp_path,
                                                                       capsys):
    """A checkpoint whose verdict cannot be checked is no endorsement: one recorded before the
    guards (which says 'better' on its score alone, as the 1,652-iteration run did while the guards
    call it not better) and one without validation are refused like a losing one, with a message
    naming the file and what is missing, and used with --force and a warning."""
    from gesturedb.cli.main import main

    wav = scott_dir / "inputs" / "2_scott_0_3_3.wav"
    ck = tmp_path / "old.pt"
    _db_checkpoints(scott_db_path, tmp_path, [("old", 0.5 if kind == "before-guards" else None)])
    if kind == "before-guards":
        _before_the_guards(ck)
        assert read_checkpoint(ck)["validation"]["verdict"]["beats_identity"] is True  # what it claims
        want = (f"gesturedb synth: error: --refiner {ck}: its validation verdict (better: score +50.0% at "
                "iteration 1) was recorded without the guards a verdict needs now, so whether it improves on the "
                "unrefined motion is unknown: it did not check |log jerk ratio|, H(speed) vs the capture, H(speed) "
                "vs the database's motion, arm bands vs the database's motion, FGD* vs the database's motion; "
                "`gesturedb refiner train DB.h5 -o "
                f"{ck} --resume --iterations 1` on the database it was trained on measures it again; --force uses "
                "it anyway")
    else:
        assert "validation" not in read_checkpoint(ck)
        want = (f"gesturedb synth: error: --refiner {ck}: no validation verdict (trained with --val-fraction 0, "
                "or before validation existed): whether it improves on the unrefined motion is unknown; train one "
                "with validation (refiner train --val-fraction, default 0.25); --force uses it anyway")
    out = tmp_path / "out.bvh"
    capsys.readouterr()
    assert main(["synth", str(scott_db_path), "--audio", str(wav), "-o", str(out), "--refiner", str(ck)]) == 2
    assert capsys.readouterr().err.strip() == want and not out.exists()
    assert main(["synth", str(scott_db_path), "--audio", str(wav), "-o", str(out), "--refiner", str(ck),
                 "--force"]) == 0
    err = capsys.readouterr().err
    assert f"warning: {ck}: " in err and "used because of --force" in err and out.exists()
    # refiner apply refines the file it is given, and says the same
    assert main(["refiner", "apply", str(ck), "--db", str(scott_db_path), "--audio", str(wav), "--input", str(out),
                 "-o", str(tmp_path / "applied.bvh")]) == 0
    err = capsys.readouterr().err
    assert f"warning: {ck}: " in err and "applied as asked (synth --refiner refuses it without --force)" in err


def test_a_partial_verdict_is_unknown_and_a_whole_one_is_not():
    identity = _Scripted._m(1.0)
    whole = V.verdict(1.0, 0.5, 3, identity=identity, best=_Scripted._m(0.5))
    assert whole["guards"] == list(V.GUARDS) and V.missing_guards(whole) == []
    older = {k: v for k, v in _Scripted._m(0.5).items() if k not in ("hellinger_db", "band_db")}
    part = V.verdict(1.0, 0.5, 3, identity=identity, best=older)
    assert part["beats_identity"] and V.missing_guards(part) == ["hellinger_db", "band_db"]
    assert V.missing_guards({k: v for k, v in whole.items() if k != "guards"}) == list(V.GUARDS)
    ref = Refiner(Generator(12, audio_channels=28, width=8), np.arange(1, 3), _FEATURES, "r.pt",
                  {"verdict": part}, 3)
    kind, message = ref.assess()
    assert kind == "unknown" and message.startswith("r.pt: its validation verdict (better: score +50.0% at iteration "
                                                    "3) was recorded without the guards") \
        and "it did not check H(speed) vs the database's motion, arm bands vs the database's motion;" in message


def test_resuming_a_checkpoint_from_before_the_guards_measures_its_best_again(tmp_path):
    """Resuming measures the best generator again on the validation windows, so the verdict saved
    next is a whole one; it draws nothing from the RNGs a resumed run continues with."""
    cfg = TrainConfig(**_CFG)
    tr = _validated(cfg, [0.5, 0.7])
    tr.save(tmp_path / "fresh.pt")
    tr.save(tmp_path / "old.pt")
    _before_the_guards(tmp_path / "old.pt")
    fresh = Trainer(_tiny(), cfg, "id", _FEATURES, validator=_Scripted(_tiny(), [0.9]))
    fresh.restore(read_checkpoint(tmp_path / "fresh.pt", training=True))
    assert fresh.remeasured is None
    seen = []

    class _Measured(_Scripted):  # the best generator, measured again: its weights must be iteration 1's
        def measure(self, channels, *, critic_gap=float("nan")):
            seen.append(channels)
            return self._m(0.6)

    old = Trainer(_tiny(), cfg, "id", _FEATURES, validator=_Measured(_tiny(), []))
    old.restore(read_checkpoint(tmp_path / "old.pt", training=True), tmp_path / "old.pt")
    assert old.remeasured == 1 and old.best["metrics"]["score"] == 0.6 and len(seen) == 1
    G = Generator(12, audio_channels=28, width=8)
    G.load_state_dict(tr.best["generator"])
    G.eval()
    with torch.no_grad():
        want = G(torch.from_numpy(old.validator.audio), torch.from_numpy(old.validator.knn)).numpy()
    np.testing.assert_array_equal(seen[0], want)
    v = old.verdict()
    assert v["beats_identity"] and v["best_iteration"] == 1 and V.missing_guards(v) == []
    old.save(tmp_path / "old.pt")
    assert V.missing_guards(read_checkpoint(tmp_path / "old.pt")["validation"]["verdict"]) == []
    fresh.step(), old.step()
    assert _same_weights(fresh.G.state_dict(), old.G.state_dict())  # the RNG states are the saved ones


def test_progress_shows_the_losses_and_the_last_validation(scott_db, tmp_path, monkeypatch):
    """On a terminal the bar's postfix holds the losses, the gradient ratio and the last validation
    score and jerk ratio; without one (a log file) the same numbers come as lines, every LOG_EVERY_S."""
    import tqdm as tqdm_module

    from gesturedb.refiner import train as T

    cfg = TrainConfig(iterations=2, batch=2, width=8, n_critic=1, stride=20, val_every=1)
    lines = []
    monkeypatch.setattr(T, "LOG_EVERY_S", 0.0)
    tr = T.train(scott_db, tmp_path / "r.pt", config=cfg, progress=True, log=lines.append)  # stderr: no terminal
    rows = [ln for ln in lines if ln.startswith("iteration ")]
    assert [r.split(":")[0] for r in rows] == ["iteration 1/2", "iteration 2/2"]
    last = tr.val_log[-1]
    assert rows[-1].startswith(f"iteration 2/2: critic {tr.history[-1]['critic']:.3f}, l1 ") and \
        rows[-1].endswith(f", val {last[1]:.3f}, jerk {last[2]:.2f}x")
    assert ", adv " in rows[-1] and ", ratio " in rows[-1]

    postfixes = []

    class _Terminal:  # an enabled bar, as on a terminal
        disable = False

        def __init__(self, *args, **kwargs):
            pass

        def update(self, n=1):
            pass

        def set_postfix(self, **kw):
            postfixes.append(kw)

        def write(self, line, file=None):
            lines.append(line)

        def close(self):
            pass

    monkeypatch.setattr(tqdm_module, "tqdm", _Terminal)
    lines.clear()
    tr = T.train(scott_db, tmp_path / "r.pt", config=cfg, progress=True, log=lines.append, overwrite=True)
    last = tr.val_log[-1]
    assert len(postfixes) == 2 and set(postfixes[-1]) == {"critic", "l1", "adv", "ratio", "val", "jerk"}
    assert postfixes[-1]["val"] == f"{last[1]:.3f}" and postfixes[-1]["jerk"] == f"{last[2]:.2f}x"
    assert not [ln for ln in lines if ln.startswith("iteration ")]  # the bar shows them
    assert any(ln.startswith("validation at iteration 2: score ") for ln in lines)
