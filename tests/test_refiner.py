"""The cGAN refiner: shapes, gradient penalty, training, exact resume, representation, checkpoints, CLI."""
from __future__ import annotations

import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="the refiner extra (torch==2.13.0) is not installed: "
                                           "pip install '.[refiner]'")

import gesturedb  # noqa: E402
from gesturedb import rotations as R  # noqa: E402
from gesturedb.errors import InputFileError  # noqa: E402
from gesturedb.refiner.data import (  # noqa: E402
    TrainingData,
    database_identity,
    exclusion,
    feature_identity,
    usable_windows,
    window_starts,
)
from gesturedb.refiner.model import Discriminator, Generator, gradient_penalty  # noqa: E402
from gesturedb.refiner.representation import (  # noqa: E402
    from_channels,
    from_channels_torch,
    moving_joints,
    to_channels,
    to_channels_torch,
)
from gesturedb.refiner.train import Refiner, TrainConfig, Trainer, read_checkpoint  # noqa: E402


def _tiny_data(W=6, C=12, T=16, seed=0) -> TrainingData:
    rng = np.random.default_rng(seed)
    F = 3 * W + T  # windows 3 frames apart
    return TrainingData(
        frame_audio=rng.standard_normal((F, 28)).astype(np.float32),
        frame_real=rng.standard_normal((F, C)).astype(np.float32),
        knn=rng.standard_normal((W, C, T)).astype(np.float32),
        joints=np.arange(1, C // 6 + 1), starts=3 * np.arange(W), ks=np.ones(W, np.int64),
    )


#: the feature identity of a three-joint skeleton, which _tiny_data's channels (joints 1 and 2) fit
_FEATURES = {"joint_names": ["root", "spine", "head"], "parents": [-1, 0, 1], "fps": 15.0, "audio_channels": 28,
             "n_mfcc": 13}


# -- model --------------------------------------------------------------------------
@pytest.mark.parametrize("T", [1, 5, 8, 13, 64, 150])
def test_generator_keeps_any_length_and_starts_as_identity(T):
    G = Generator(18, width=16).eval()
    a, x = torch.randn(2, 28, T), torch.randn(2, 18, T)
    y = G(a, x)
    assert y.shape == (2, 18, T)
    # the last block starts at zero: an untrained refiner returns its input exactly
    assert torch.equal(y, x)


@pytest.mark.parametrize("T", [8, 16, 64, 100])
def test_discriminator_gives_one_score_per_sequence(T):
    D = Discriminator(18, width=16)
    assert D(torch.randn(3, 28, T), torch.randn(3, 18, T)).shape == (3,)


def test_generator_has_the_papers_blocks():
    G = Generator(18, width=16)
    assert len(G.enc) == 8 and len(G.dec) == 7  # + the final single Conv1d = 8 decoder blocks
    assert isinstance(G.out, torch.nn.Conv1d)
    D = Discriminator(18, width=16)
    assert len(D.blocks) == 6 and isinstance(D.fc, torch.nn.Linear)


def test_gradient_penalty_of_a_linear_critic_is_known():
    # D(a, x) = <wa, a> + <wx, x>: the gradient is (wa, wx) everywhere, its norm known exactly
    torch.manual_seed(0)
    wa, wx = torch.randn(1, 28, 8), torch.randn(1, 6, 8)

    def critic(a, x):
        return (a * wa).flatten(1).sum(1) + (x * wx).flatten(1).sum(1)

    norm = float(torch.sqrt((wa ** 2).sum() + (wx ** 2).sum()))
    gp = gradient_penalty(critic, torch.randn(4, 28, 8), torch.randn(4, 6, 8), torch.randn(4, 28, 8),
                          torch.randn(4, 6, 8), torch.rand(4, 1, 1))
    assert float(gp) == pytest.approx((norm - 1) ** 2, rel=1e-5)
    # a critic with unit gradient norm pays no penalty
    s = 1 / norm
    gp1 = gradient_penalty(lambda a, x: critic(a, x) * s, torch.randn(2, 28, 8), torch.randn(2, 6, 8),
                           torch.randn(2, 28, 8), torch.randn(2, 6, 8), torch.rand(2, 1, 1))
    assert float(gp1) == pytest.approx(0.0, abs=1e-8)


def test_critic_updates_lower_the_critic_loss_on_a_tiny_batch():
    # augmentation off: this is about the critic update itself, on the very windows it sees
    tr = Trainer(_tiny_data(), TrainConfig(batch=4, width=16, n_critic=1, crop=1.0, warp=0.0), "id", {})
    data = tr.data
    a, real, knn = (torch.from_numpy(f(np.arange(4))) for f in (data.audio, data.real, data.fake))

    def wasserstein():
        with torch.no_grad():
            fake = tr.G(a, knn)
            return float(tr.D(a, fake).mean() - tr.D(a, real).mean())

    before = wasserstein()
    for _ in range(20):
        tr.critic_step()
    assert wasserstein() < before - 1e-3


# -- resume -------------------------------------------------------------------------
def test_resume_gives_the_weights_of_an_uninterrupted_run(tmp_path):
    cfg = TrainConfig(batch=3, width=8, n_critic=2, iterations=4, seed=7)
    straight = Trainer(_tiny_data(), cfg, "id", _FEATURES)
    for _ in range(4):
        straight.step()

    first = Trainer(_tiny_data(), cfg, "id", _FEATURES)
    for _ in range(2):
        first.step()
    first.save(tmp_path / "ck.pt")
    torch.manual_seed(12345)  # whatever happened in between must not matter
    second = Trainer(_tiny_data(), cfg, "id", _FEATURES)
    second.restore(read_checkpoint(tmp_path / "ck.pt", training=True))
    for _ in range(2):
        second.step()
    assert second.iteration == 4
    for name in ("G", "D"):
        sa, sb = getattr(straight, name).state_dict(), getattr(second, name).state_dict()
        for k in sa:
            assert torch.equal(sa[k], sb[k]), f"{name}.{k} differs after resume"
    assert [h["critic"] for h in straight.history] == [h["critic"] for h in second.history]


def test_checkpoint_loading_runs_no_code(tmp_path):
    class Payload:
        def __reduce__(self):
            return (print, ("owned",))

    torch.save({"format": 1, "x": Payload()}, tmp_path / "evil.pt")
    with pytest.raises(InputFileError, match="evil.pt.*expected a gesturedb refiner checkpoint"):
        read_checkpoint(tmp_path / "evil.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(InputFileError, match="junk.pt"):
        read_checkpoint(tmp_path / "junk.pt")


# -- representation (real motion) ----------------------------------------------------
def test_representation_round_trip_is_exact(scott_db):
    q = np.asarray(scott_db.local_rotations[:300], dtype=np.float64)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    joints = moving_joints(scott_db.local_rotations)
    assert 0 not in joints and len(joints) > 20
    back = from_channels(to_channels(q, joints), q, joints)
    # same rotation (q and -q are one) for every joint and frame
    dot = np.abs(np.sum(back * q, axis=-1))
    assert np.max(np.arccos(np.clip(dot, -1, 1)) * 2) < 1e-6
    assert np.array_equal(back[:, 0], q[:, 0])  # the root is never touched


def test_any_six_numbers_give_a_rotation():
    rng = np.random.default_rng(1)
    base = R.from_axis_angle(rng.standard_normal((5, 4, 3)))
    out = from_channels(rng.standard_normal((5, 12)), base, np.array([1, 3]))
    assert np.allclose(np.linalg.norm(out, axis=-1), 1.0)
    assert np.array_equal(out[:, [0, 2]], base[:, [0, 2]])


def test_torch_conversions_agree_with_numpy_in_every_shepperd_branch(scott_db):
    # refining uses float32 torch versions of to/from_channels; the numpy ones are the oracle
    rng = np.random.default_rng(2)
    q = np.asarray(scott_db.local_rotations[:200], dtype=np.float64)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    joints = moving_joints(scott_db.local_rotations)
    x = to_channels_torch(q, joints)
    assert x.dtype == torch.float32 and tuple(x.shape) == (1, 6 * len(joints), 200)
    assert np.allclose(x[0].numpy().T, to_channels(q, joints), atol=1e-6)
    # random 6D numbers (any branch), and near-180-degree turns about x, y, z: branches 1, 2, 3,
    # where w ~ 0 and picking the wrong branch would lose all precision
    six = rng.standard_normal((200, 6 * len(joints)))
    cases = [six]
    for axis in range(3):
        turn = np.zeros((200, len(joints), 4))
        turn[..., 1 + axis] = 1.0
        turn[..., 0] = rng.uniform(-1e-3, 1e-3, turn.shape[:2])
        turn[..., 1 + (axis + 1) % 3] = rng.uniform(-1e-3, 1e-3, turn.shape[:2])
        turn /= np.linalg.norm(turn, axis=-1, keepdims=True)
        full = q.copy()
        full[:, joints] = turn
        cases.append(to_channels(full, joints))
    for c in cases:
        expect = from_channels(c, q, joints)
        got = from_channels_torch(torch.from_numpy(c.T.astype(np.float32)), q, joints)
        # the same quaternion, same sign (both keep the base's hemisphere), to float32 precision
        assert np.abs(got - expect).max() < 1e-5
        assert np.array_equal(got[:, 0], q[:, 0])
    # a cropped (strided) view, as the generator returns, gives the same numbers
    padded = torch.from_numpy(np.pad(six.T, ((0, 0), (0, 8))).astype(np.float32))[:, :200]
    assert np.array_equal(from_channels_torch(padded, q, joints),
                          from_channels_torch(torch.from_numpy(six.T.astype(np.float32)), q, joints))


# -- training data (real database) ---------------------------------------------------
def test_training_windows_never_see_their_own_neighbourhood(scott_db):
    starts = window_starts(scott_db)
    assert np.all(np.diff(starts) == 5)  # one recording, stride 5
    ex = exclusion(scott_db, starts)
    seg = scott_db.chunks
    for i in (0, len(starts) // 2, len(starts) - 1):
        a = starts[i]
        overlap = (seg.start + seg.length > a) & (seg.start < a + 64)
        assert ex[i][overlap].all()
        assert not ex[i].all()  # something is left to search


# -- the real pipeline: CLI train, resume, synth --refiner, apply ------------------------
@pytest.mark.slow
def test_cli_train_resume_synth_and_apply(scott_db_path, scott_dir, tmp_path):
    def gdb(*args):
        return subprocess.run([sys.executable, "-m", "gesturedb.cli", *map(str, args)],
                              capture_output=True, text=True, timeout=600)

    ck = tmp_path / "refiner.pt"
    r = gdb("refiner", "train", scott_db_path, "-o", ck, "--iterations", 2, "--batch", 4, "--stride", 0)
    assert r.returncode != 0 and "--stride: expected a positive integer, got 0" in r.stderr
    r = gdb("refiner", "train", scott_db_path, "-o", ck, "--iterations", 2, "--batch", 4, "--threads", 1,
            "--seed", 5, "--stride", 9)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "refiner.pt.data.h5").is_file() and "searching the database" in r.stderr
    # resumed without --seed: it keeps its own seed, so its cached training data is still its own
    r = gdb("refiner", "train", scott_db_path, "-o", ck, "--iterations", 3, "--batch", 4, "--resume")
    assert r.returncode == 0, r.stderr
    assert "trained 1 iterations (3 in all)" in r.stdout and "searching the database" not in r.stderr
    assert read_checkpoint(ck)["iteration"] == 3 and read_checkpoint(ck)["config"]["seed"] == 5
    # and its own stride: the cached windows are every 9th frame's, not the default 5th
    assert read_checkpoint(ck)["config"]["stride"] == 9 and "stride 9" in read_checkpoint(ck)["data"]
    with gesturedb.open(scott_db_path) as db, h5py.File(tmp_path / "refiner.pt.data.h5", "r") as f:
        assert f.attrs["stride"] == 9
        # every 9th frame's windows but those straddling the validation cut (the last 25 %)
        every = window_starts(db, stride=9)
        np.testing.assert_array_equal(f["starts"][:], every[usable_windows(db, every, 0.25)])
        assert 0 < f["val"][:].sum() < len(f["starts"]) and len(every) < len(window_starts(db))
    # checkpoint and cache went through temporary siblings that were renamed: nothing else is left
    # (but the cache's write lock, as beside every database)
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.endswith(".lock")) == [
        "refiner.pt", "refiner.pt.data.h5"]

    wav = scott_dir / "inputs" / "2_scott_0_3_3.wav"
    plain, refined = tmp_path / "knn.bvh", tmp_path / "refined.bvh"
    assert gdb("synth", scott_db_path, "--audio", wav, "-o", plain).returncode == 0
    # three iterations do not beat the identity on validation: refused, then used with --force, and the
    # checkpoint keeps the identity, so forced it changes nothing
    r = gdb("synth", scott_db_path, "--audio", wav, "-o", refined, "--refiner", ck)
    assert r.returncode == 2 and "no trained generator beat the unrefined motion" in r.stderr and "--force" in r.stderr
    assert not refined.exists()
    r = gdb("synth", scott_db_path, "--audio", wav, "-o", refined, "--refiner", ck, "--force")
    assert r.returncode == 0, r.stderr
    assert "warning: " in r.stderr and "used because of --force" in r.stderr
    from gesturedb.io import read_motion

    a, b = read_motion(plain), read_motion(refined)
    assert a.n_frames == b.n_frames
    assert refined.read_bytes() == plain.read_bytes()
    applied = tmp_path / "applied.bvh"
    r = gdb("refiner", "apply", ck, "--db", scott_db_path, "--audio", wav, "--input", plain, "-o", applied)
    assert r.returncode == 0, r.stderr
    assert read_motion(applied).n_frames == a.n_frames


def test_a_checkpoint_for_another_skeleton_is_refused(scott_db, tmp_path):
    feats = feature_identity(scott_db)
    tr = Trainer(_tiny_data(), TrainConfig(width=8), database_identity(scott_db),
                 dict(feats, joint_names=feats["joint_names"][:-1], parents=feats["parents"][:-1]))
    tr.save(tmp_path / "other.pt")
    last = feats["joint_names"][-1]
    n = len(feats["joint_names"])
    with pytest.raises(InputFileError, match=rf"other.pt.*skeleton joints: the refiner was trained for {n - 1} "
                                             rf"entries, database .* has {n}; only in the database: entry {n - 1} "
                                             rf"'{last}'; "):
        Refiner.load(tmp_path / "other.pt", db=scott_db)
    # same length, one joint renamed: the message names it, not "different entries"
    names = list(feats["joint_names"])
    old, names[3] = names[3], "Renamed"
    Trainer(_tiny_data(), TrainConfig(width=8), database_identity(scott_db),
            dict(feats, joint_names=names)).save(tmp_path / "renamed.pt")
    with pytest.raises(InputFileError, match=rf"skeleton joints: the refiner was trained for {n} entries, database .* "
                                             rf"has {n}; 1 of the first {n} differ: entry 3: 'Renamed' \(refiner\) vs "
                                             rf"'{old}' \(database\); train a refiner"):
        Refiner.load(tmp_path / "renamed.pt", db=scott_db)


def test_without_torch_the_commands_say_how_to_install(tmp_path):
    code = ("import sys; sys.modules['torch'] = None\n"
            "from gesturedb.cli.main import main\n"
            f"sys.exit(main(['refiner', 'train', 'x.h5', '-o', {str(tmp_path / 'r.pt')!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 2
    assert "pip install 'gesturedb[refiner]'" in r.stderr


def test_refining_keeps_the_root_and_the_planted_legs(scott_db):
    from gesturedb.io.joints import leg_joints

    joints = moving_joints(scott_db.local_rotations)
    G = Generator(6 * len(joints), width=8)
    torch.nn.init.normal_(G.out.weight, std=0.1)  # a generator that changes things
    ref = Refiner(G, joints, feature_identity(scott_db))
    motion = scott_db.motion(scott_db.recordings[0].name, 0.0, 6.0)
    audio = np.random.default_rng(0).standard_normal((motion.n_frames, 28)).astype(np.float32)
    out = ref.refine(motion, audio)
    legs = leg_joints(scott_db.skeleton.names, scott_db.skeleton.parents)
    assert len(legs) == 8  # SMPL-X: hip, knee, ankle, foot per side
    assert np.array_equal(out.rotations[:, legs], np.asarray(motion.rotations, dtype=np.float64)[:, legs])
    assert np.array_equal(out.root_positions, motion.root_positions)
    arms = [j for j in joints if j not in set(legs)]
    assert not np.allclose(out.rotations[:, arms], motion.rotations[:, arms])


def test_refining_runs_on_its_own_threads_and_gives_torch_its_setting_back(scott_db):
    """Refining takes REFINE_THREADS intra-op threads whatever torch was set to (two threads were 4x
    slower on a shared machine), puts torch's setting back, and its result does not depend on either."""
    from gesturedb.refiner import train as T

    joints = moving_joints(scott_db.local_rotations)
    G = Generator(6 * len(joints), width=8)
    torch.nn.init.normal_(G.out.weight, std=0.1)
    motion = scott_db.motion(scott_db.recordings[0].name, 0.0, 6.0)
    audio = np.random.default_rng(0).standard_normal((motion.n_frames, 28)).astype(np.float32)
    seen = []
    forward = G.forward
    G.forward = lambda *a: (seen.append(torch.get_num_threads()), forward(*a))[1]
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        one = Refiner(G, joints, feature_identity(scott_db)).refine(motion, audio)
        two = Refiner(G, joints, feature_identity(scott_db), threads=2).refine(motion, audio)
        assert seen == [T.REFINE_THREADS, 2] and torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)
    np.testing.assert_allclose(one.rotations, two.rotations, atol=1e-6)
    with torch.no_grad():  # inference mode changes no number
        x = to_channels_torch(motion.rotations, joints)
        ref = from_channels_torch(forward(torch.from_numpy(np.ascontiguousarray(audio.T[None])), x)[0],
                                  motion.rotations, joints)
    arms = [j for j in joints if j not in set(T.leg_joints(scott_db.skeleton.names, scott_db.skeleton.parents))]
    np.testing.assert_allclose(one.rotations[:, arms], ref[:, arms], atol=1e-6)
    with pytest.raises(gesturedb.ParameterError, match=r"^threads: expected a positive integer, got 0$"):
        Refiner(G, joints, feature_identity(scott_db), threads=0)


def test_refiner_commands_never_write_over_their_inputs(scott_db_path, tmp_path):
    from gesturedb.cli.main import main

    assert main(["refiner", "train", str(scott_db_path), "-o", str(scott_db_path)]) == 2
    assert main(["refiner", "apply", str(tmp_path / "r.pt"), "--db", str(scott_db_path), "--audio", "a.wav",
                 "--input", str(scott_db_path), "-o", str(scott_db_path)]) == 2
    assert scott_db_path.is_file()


# -- nothing lost, nothing poisoned (issue 41, cases 6 and 13) ----------------------------
def _cache(db, path, *, n=8, poison=None) -> None:
    """A training-data cache for ``db`` made by hand (its fakes are the real windows), as
    train() with seed 0 and stride 5 reads it; ``poison``: (dataset, index, value) to plant."""
    from gesturedb.refiner.data import cache_settings, frame_arrays

    joints = moving_joints(db.local_rotations)
    starts = window_starts(db)[:n]
    _, real = frame_arrays(db, joints)
    arrays = {"starts": starts, "ks": np.ones(n, np.int64), "joints": joints, "val": np.zeros(n, bool),
              "knn": np.stack([real[s:s + 64].T for s in starts]).astype(np.float32)}
    if poison is not None:
        name, index, value = poison
        arrays[name][index] = value
    with h5py.File(path, "w") as h5:
        for k, v in cache_settings(db, seed=0, window=64, stride=5).items():
            h5.attrs[k] = v
        for k, v in arrays.items():
            h5[k] = v


_SMALL = dict(iterations=1, batch=2, width=8, n_critic=1, val_fraction=0.0)  # the hand-made cache has no split


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("poison, match", [
    (("knn", (3, 5, 7), np.nan), r"knn: expected finite values, got nan in window 3 \(channel 5, frame 7\)"),
    (("knn", (0, 0, 0), np.inf), r"knn: expected finite values, got inf in window 0"),
    (("joints", 0, 999), r"joints: expected ascending joint indices from 0 to 54, got \[999, "),
    (("starts", 2, 10**9), r"starts: expected first frames from 0 to 889 \(windows of 64 frames in 953\), got 1000000000"),
    (("ks", 1, 0), r"ks: expected k from 1 to 15, got 0"),
], ids=["nan", "inf", "joint-999", "start-1e9", "k-0"])
def test_a_poisoned_or_crafted_cache_is_refused_and_the_checkpoint_kept(poison, match, scott_db, tmp_path):
    """One NaN in the cached fakes made every weight NaN, exited 0 and overwrote the good
    checkpoint; a crafted cache gave IndexError. Now: one line naming the cache and the dataset,
    and the checkpoint as it was (a resumed run, through the CLI)."""
    from gesturedb.refiner.train import train

    ck = tmp_path / "r.pt"
    _cache(scott_db, tmp_path / "r.pt.data.h5")
    train(scott_db, ck, config=TrainConfig(**_SMALL))
    before = ck.read_bytes()
    _cache(scott_db, tmp_path / "r.pt.data.h5", poison=poison)
    with pytest.raises(InputFileError, match=rf"^{tmp_path}/r\.pt\.data\.h5: {match}.*delete the file"):
        train(scott_db, ck, config=TrainConfig(**dict(_SMALL, iterations=2)), resume=True)
    assert ck.read_bytes() == before


def test_cli_resume_from_a_poisoned_cache_exits_2_with_one_line(scott_db_path, tmp_path, capsys):
    from gesturedb.cli.main import main
    from gesturedb.refiner.train import train

    ck = tmp_path / "r.pt"
    with gesturedb.open(scott_db_path) as db:
        _cache(db, tmp_path / "r.pt.data.h5")
        train(db, ck, config=TrainConfig(**_SMALL))
        _cache(db, tmp_path / "r.pt.data.h5", poison=("knn", (1, 2, 3), np.nan))
    before = ck.read_bytes()
    capsys.readouterr()
    assert main(["refiner", "train", str(scott_db_path), "-o", str(ck), "--iterations", "3", "--resume"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith(f"gesturedb refiner: error: {ck}.data.h5: knn: expected finite values, got nan"), line
    assert ck.read_bytes() == before


def test_a_non_finite_loss_stops_training_before_any_save(scott_db, tmp_path, monkeypatch):
    """Training data with a NaN that got past the cache's check (planted after it): the first
    non-finite loss stops the run with an error, before the save due at every iteration, and
    the resumed checkpoint stays as it was."""
    from gesturedb.refiner import train as T

    ck = tmp_path / "r.pt"
    _cache(scott_db, tmp_path / "r.pt.data.h5")
    T.train(scott_db, ck, config=TrainConfig(**_SMALL))
    before = ck.read_bytes()
    real_load = T.load_cache

    def poisoned(*a, **k):
        data = real_load(*a, **k)
        data.frame_audio[:] = np.nan
        return data

    monkeypatch.setattr(T, "load_cache", poisoned)
    with pytest.raises(gesturedb.GestureDBError,
                       match=rf"^{ck}: training stopped at iteration 2: critic loss: expected a finite value, got "
                             r"nan; the checkpoint of iteration 1 is kept$"):
        T.train(scott_db, ck, config=TrainConfig(**dict(_SMALL, iterations=5, checkpoint_every_s=0.0)), resume=True)
    assert ck.read_bytes() == before
    # and weights that did go non-finite are never written, whatever the loss said
    tr = Trainer(_tiny_data(), TrainConfig(width=8), "id", _FEATURES)
    with torch.no_grad():
        tr.G.out.bias[0] = float("inf")
    with pytest.raises(gesturedb.GestureDBError, match=r"^\S+r\.pt: not saved: generator out\.bias: expected finite "
                                                       r"values, got inf after iteration 0; the previous checkpoint"):
        tr.save(ck)
    assert ck.read_bytes() == before


def test_an_existing_checkpoint_is_replaced_only_with_overwrite(scott_db_path, tmp_path, capsys):
    from gesturedb.cli.main import main
    from gesturedb.refiner.train import train

    ck = tmp_path / "r.pt"
    with gesturedb.open(scott_db_path) as db:
        _cache(db, tmp_path / "r.pt.data.h5")
        train(db, ck, config=TrainConfig(**dict(_SMALL, iterations=2)))
    before = ck.read_bytes()
    argv = ["refiner", "train", str(scott_db_path), "-o", str(ck), "--iterations", "1", "--batch", "2"]
    capsys.readouterr()
    assert main(argv) == 2
    assert _one_line(capsys.readouterr().err) == (
        f"gesturedb refiner: error: {ck}: a file already exists here; continue its training with --resume, or "
        "start afresh over it with --overwrite")
    assert ck.read_bytes() == before
    with pytest.raises(SystemExit):
        main(argv + ["--resume", "--overwrite"])
    assert "not allowed with argument" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0
    assert read_checkpoint(ck)["iteration"] == 1 and ck.read_bytes() != before


def _checkpoint(tmp_path, **change):
    """A real checkpoint (tiny training data, three-joint skeleton) with entries changed or removed (None)."""
    tr = Trainer(_tiny_data(), TrainConfig(width=8, batch=2, n_critic=1), "id", _FEATURES)
    tr.step()
    ck = tr.state()
    for k, v in change.items():
        if v is None:
            del ck[k]
        else:
            ck[k] = v(ck) if callable(v) else v
    path = tmp_path / "c.pt"
    torch.save(ck, path)
    return path


def _nan_weight(ck):
    g = dict(ck["generator"])
    g["enc.0.0.weight"] = g["enc.0.0.weight"].clone()
    g["enc.0.0.weight"][0, 0, 0] = float("nan")
    return g


@pytest.mark.parametrize("change, match", [
    (dict(generator=None), r"generator: missing; expected a gesturedb refiner checkpoint with this entry"),
    (dict(config="width=8"), r"config: expected dict, got str"),
    (dict(joints=lambda ck: ck["joints"].tolist()), r"joints: expected Tensor, got list"),
    (dict(config=lambda ck: dict(ck["config"], width=30000)), r"config: width: expected an integer from 1 to 1024, "
                                                              r"got 30000"),
    (dict(config=lambda ck: dict(ck["config"], colour=1)), r"config: expected settings among .*, got 'colour'"),
    (dict(config=lambda ck: dict(ck["config"], width=16)), r"generator: does not fit the model of the checkpoint's "
                                                           r"settings \(Error\(s\) in loading state_dict"),
    (dict(features=lambda ck: dict(ck["features"], audio_channels="28")),
     r"features\.audio_channels: expected an integer from 1 to 1024, got '28'"),
    (dict(features=lambda ck: {}), r"features\.joint_names: expected 1 to 1024 joint names, got NoneType"),
    (dict(joints=lambda ck: torch.tensor([1, 999])), r"joints: expected ascending joint indices from 0 to 2, got \[1, 999\]"),
    (dict(generator=_nan_weight), r"generator: enc\.0\.0\.weight: expected finite values, got nan"),
    (dict(format=2), r"format: expected a gesturedb refiner checkpoint of format 1, got 2"),
    (dict(format=lambda ck: torch.ones(2)), r"format: expected a gesturedb refiner checkpoint of format 1, got Tensor"),
    (dict(validation={"log": [], "verdict": {"beats_identity": True, "identity_score": 1.0, "best_score": 0.5,
                                             "improvement": 0.5, "best_iteration": 1, "guards": "all"}},
          best_generator=lambda ck: ck["generator"]),
     r"validation\.verdict\.guards: expected a list of guard names, got 'all'"),
    (dict(validation={"log": [], "trained_best": {"iteration": "3", "metrics": {}}}),
     r"validation\.trained_best: expected None or an iteration \(int\) and its metrics"),
], ids=["missing", "mistyped", "joints-list", "width-30000", "unknown-setting", "width-mismatch", "audio-str",
        "no-features", "joint-999", "nan-weight", "format", "format-tensor", "guards-str", "trained-best-str"])  # format-tensor: found by fuzz_checkpoint
def test_a_damaged_checkpoint_is_one_line_naming_the_file_and_entry(change, match, tmp_path):
    """Missing or mistyped entries gave KeyError, AttributeError or TypeError; a width of 30000
    tried to allocate 10.8 GB; NaN weights were loaded. All are refused on load, before any
    model is built from them."""
    path = _checkpoint(tmp_path, **change)
    with pytest.raises(InputFileError, match=rf"^{path}: {match}") as info:
        Refiner.load(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("change, match", [
    (dict(opt_g=None), r"opt_g: missing"),
    (dict(history=lambda ck: [[1, "x", 0.0, 0.0]]), r"history: expected at most 1 rows of 4 or 5 numbers"),
    (dict(iteration=-1), r"iteration: expected an integer from 0 to 1000000000, got -1"),
    (dict(discriminator=_nan_weight), r"discriminator: enc\.0\.0\.weight: expected finite values, got nan"),
    (dict(sampler_state=lambda ck: ck["sampler_state"].float()), r"sampler_state: expected a random generator state"),
], ids=["no-optimiser", "history", "iteration", "nan-critic", "sampler"])
def test_a_damaged_checkpoint_is_refused_on_resume(change, match, tmp_path):
    path = _checkpoint(tmp_path, **change)
    with pytest.raises(InputFileError, match=rf"^{path}: {match}"):
        read_checkpoint(path, training=True)


def test_an_empty_or_foreign_checkpoint_file_is_one_line(tmp_path, scott_db_path, capsys):
    """A 0-byte .pt crashed the error handler itself (the first line of an empty message)."""
    import zipfile

    from gesturedb.cli.main import main

    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(InputFileError, match=rf"^{empty}: expected a gesturedb refiner checkpoint, got an empty file"):
        read_checkpoint(empty)
    huge = tmp_path / "huge.pt"  # a zip whose member claims more bytes than the file has
    with zipfile.ZipFile(huge, "w") as z:
        z.writestr("c/data.pkl", b"x" * 100)
    data = bytearray(huge.read_bytes())
    i = data.rindex(b"PK\x01\x02")  # central directory entry: uncompressed size at +24
    data[i + 24:i + 28] = (2**31).to_bytes(4, "little")
    huge.write_bytes(bytes(data))
    with pytest.raises(InputFileError, match=r"huge\.pt: c/data\.pkl: expected an uncompressed member of at most"):
        read_checkpoint(huge)
    wav = tmp_path / "a.wav"
    wav.write_bytes(b"")
    capsys.readouterr()
    assert main(["refiner", "apply", str(empty), "--db", str(scott_db_path), "--audio", str(wav), "--input",
                 str(tmp_path / "in.bvh"), "-o", str(tmp_path / "out.bvh")]) == 2
    assert _one_line(capsys.readouterr().err) == (f"gesturedb refiner: error: {empty}: expected a gesturedb refiner "
                                                  "checkpoint, got an empty file (0 bytes)")


def _full_after(limit):
    """An ``open`` for gesturedb.io.atomic whose files take ``limit`` bytes, then say the disk is full."""
    import builtins
    import errno

    class Full:
        def __init__(self, f):
            self.f, self.left = f, limit

        def write(self, b):
            n = len(memoryview(b).cast("B"))
            if n > self.left:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            self.left -= n
            return self.f.write(b)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    return lambda *a, **k: Full(builtins.open(*a, **k))



@pytest.mark.parametrize("disk", ["injected", "tmpfs"])
def test_disk_full_while_saving_a_checkpoint_keeps_the_previous_one(disk, tmp_path, monkeypatch):
    """torch reported a full disk as ``unexpected pos``: now one line naming the checkpoint and
    the disk's reason, the previous checkpoint byte for byte, no temporary file."""
    import contextlib

    from gesturedb.io import atomic

    tr = Trainer(_tiny_data(), TrainConfig(width=64, batch=2, n_critic=1), "id", _FEATURES)
    if disk == "tmpfs":
        folder = tmp_path / "small"
        folder.mkdir()
        p = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1200k", "tmpfs", str(folder)], capture_output=True,
                           text=True)
        if p.returncode != 0:
            pytest.skip(f"cannot mount a small tmpfs here ({p.stderr.strip()}); the injected variant runs")
        cleanup = lambda: subprocess.run(["umount", "-l", str(folder)], capture_output=True)  # noqa: E731
    else:
        folder, cleanup = tmp_path, (lambda: None)
    try:
        ck = folder / "r.pt"
        tr.save(ck)  # about 0.8 MB
        before = ck.read_bytes()
        tr.step()
        if disk == "injected":
            monkeypatch.setattr(atomic, "open", _full_after(100_000), raising=False)
        with pytest.raises(InputFileError, match=rf"^{ck}: cannot write: No space left on device$"):
            tr.save(ck)
        assert ck.read_bytes() == before
        assert sorted(p.name for p in folder.iterdir()) == ["r.pt"]
        with contextlib.suppress(Exception):
            monkeypatch.undo()
    finally:
        cleanup()


def test_cli_resume_from_nan_weights_exits_2_and_keeps_the_file(scott_db_path, tmp_path, capsys):
    """Resuming from a checkpoint whose weights are NaN exited 0 (and trained on NaN): refused."""
    from gesturedb.cli.main import main
    from gesturedb.refiner.train import train

    ck = tmp_path / "r.pt"
    with gesturedb.open(scott_db_path) as db:
        _cache(db, tmp_path / "r.pt.data.h5")
        train(db, ck, config=TrainConfig(**_SMALL))
    state = torch.load(ck, weights_only=True)
    state["generator"] = _nan_weight(state)
    torch.save(state, ck)
    before = ck.read_bytes()
    capsys.readouterr()
    for argv in (["refiner", "train", str(scott_db_path), "-o", str(ck), "--iterations", "2", "--resume"],
                 ["refiner", "apply", str(ck), "--db", str(scott_db_path), "--audio", str(tmp_path / "a.wav"),
                  "--input", str(tmp_path / "in.bvh"), "-o", str(tmp_path / "out.bvh")]):
        assert main(argv) == 2
        assert _one_line(capsys.readouterr().err) == (
            f"gesturedb refiner: error: {ck}: generator: enc.0.0.weight: expected finite values, got nan")
    assert ck.read_bytes() == before


def test_training_threads_default_to_the_available_cpus_and_threads_is_honoured(scott_db, tmp_path, monkeypatch):
    """torch's own default counts the machine's cores and ignores a CPU quota: training takes
    gesturedb.threads.available_cpus() unless told, and gives torch its setting back after."""
    from gesturedb.refiner import train as T

    seen = []
    real_step = T.Trainer.step

    def step(self):
        seen.append(torch.get_num_threads())
        return real_step(self)

    monkeypatch.setattr(T.Trainer, "step", step)
    monkeypatch.setattr(T, "available_cpus", lambda: 1)  # what a `taskset -c 0` or a 1-CPU quota gives
    _cache(scott_db, tmp_path / "r.pt.data.h5")
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        T.train(scott_db, tmp_path / "r.pt", config=TrainConfig(**_SMALL))
        assert seen == [1] and torch.get_num_threads() == 3
        T.train(scott_db, tmp_path / "r.pt", config=TrainConfig(**dict(_SMALL, iterations=2)), resume=True, threads=2)
        assert seen == [1, 2] and torch.get_num_threads() == 3
        with pytest.raises(gesturedb.ParameterError, match=r"^threads: expected a positive integer or None, got 0$"):
            T.train(scott_db, tmp_path / "r.pt", config=TrainConfig(**_SMALL), overwrite=True, threads=0)
    finally:
        torch.set_num_threads(before)
