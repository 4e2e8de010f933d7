"""The refiner's training data: per-frame real windows, fakes assembled on worker
processes and kept in a memory-mapped cache file, identical whichever way it is made."""
from __future__ import annotations

import os

import h5py
import numpy as np
import pytest

from gesturedb.refiner import data as D
from gesturedb.refiner.representation import to_channels


@pytest.fixture(scope="module")
def serial(scott_db_path):
    """Every 10th window, made in this process, in memory (the reference)."""
    import gesturedb

    with gesturedb.open(scott_db_path) as db:
        return D.make_training_data(db, seed=2, stride=10)


def _same(a: D.TrainingData, b: D.TrainingData) -> None:
    idx = np.arange(a.n_windows)
    assert b.n_windows == a.n_windows
    for name in ("frame_audio", "frame_real", "starts", "ks", "joints"):
        np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
    for name in ("audio", "real", "fake"):
        np.testing.assert_array_equal(getattr(b, name)(idx), getattr(a, name)(idx), err_msg=name)


def _files(folder) -> list[str]:
    """What a folder holds (a write lock file exists only while it is held: none is left)."""
    return sorted(os.listdir(folder))


def test_windows_are_the_database_frames(scott_db, serial):
    """real(w) and audio(w) slice the per-frame arrays: the same values as converting
    the window's own frames (the form the data had when it was stored per window)."""
    rot = scott_db.local_rotations
    audio = np.concatenate([scott_db.audio_features, scott_db.audio_deltas], axis=1)
    assert serial.n_windows > 80 and (serial.ks > 1).any()
    idx = np.array([0, 7, serial.n_windows - 1, 7])  # any order, repeats allowed (batches draw with replacement)
    real, aud = serial.real(idx), serial.audio(idx)
    assert real.shape == (4, serial.channels, 64) and real.dtype == np.float32 and real.flags.c_contiguous
    for row, w in enumerate(idx):
        a = serial.starts[w]
        np.testing.assert_array_equal(real[row], to_channels(rot[a:a + 64], serial.joints).T.astype(np.float32))
        np.testing.assert_array_equal(aud[row], audio[a:a + 64].T.astype(np.float32))
    # the fake is an assembled k-NN path, not the window itself (its own neighbourhood is excluded)
    assert not np.allclose(serial.fake([0]), serial.real([0]))


def test_worker_processes_and_the_cache_give_the_serial_data(scott_db, serial, tmp_path):
    cache = tmp_path / "r.pt.data.h5"
    calls = []
    made = D.make_training_data(scott_db, seed=2, stride=10, workers=2, cache=cache,
                                progress=lambda *a: calls.append(a))
    _same(serial, made)
    assert isinstance(made.knn, np.memmap) and not made.knn.flags.writeable  # the fakes stay on disk
    W = serial.n_windows
    done = [c[1] for c in calls if c[0] == "assembly"]
    assert done == sorted(done) and done[-1] == W and len(done) == -(-W // 32)  # chunks of 32, in order
    assert _files(tmp_path) == ["r.pt.data.h5"]  # the temporary sibling was renamed
    with h5py.File(cache, "r") as h5:  # a plain HDF5 file: the fakes and what they belong to
        assert h5["knn"].shape == (W, serial.channels, 64) and int(h5.attrs["seed"]) == 2
        np.testing.assert_array_equal(h5["starts"][()], serial.starts)

    settings = D.cache_settings(scott_db, seed=2, window=64, stride=10)
    _same(serial, D.load_cache(cache, scott_db, settings))
    for other in ({"seed": 3}, {"stride": 5}, {"identity": "0" * 16}, {"format": 1}):
        assert D.load_cache(cache, scott_db, dict(settings, **other)) is None, other
    assert D.load_cache(tmp_path / "none.h5", scott_db, settings) is None


def test_a_damaged_cache_is_made_again_and_a_failed_one_leaves_nothing(scott_db, serial, tmp_path, monkeypatch):
    cache = tmp_path / "c.h5"
    settings = D.cache_settings(scott_db, seed=2, window=64, stride=10)
    cache.write_bytes(b"not hdf5")
    assert D.load_cache(cache, scott_db, settings) is None
    D.make_training_data(scott_db, seed=2, stride=10, cache=cache)
    size = cache.stat().st_size
    with open(cache, "r+b") as f:  # cut off the end of the fakes
        f.truncate(size - 4096)
    assert D.load_cache(cache, scott_db, settings) is None

    D.make_training_data(scott_db, seed=2, stride=10, cache=cache)
    before = cache.read_bytes()
    real_assemble = D.assemble_windows
    n = {"calls": 0}

    def fail_on_the_third_chunk(*args):
        n["calls"] += 1
        if n["calls"] == 3:
            raise KeyboardInterrupt
        return real_assemble(*args)

    monkeypatch.setattr(D, "assemble_windows", fail_on_the_third_chunk)
    with pytest.raises(KeyboardInterrupt):
        D.make_training_data(scott_db, seed=2, stride=10, cache=cache)
    assert _files(tmp_path) == ["c.h5"] and cache.read_bytes() == before


def test_training_from_the_cache_is_training_from_memory(scott_db, serial, tmp_path):
    """Batches sliced from the per-frame arrays and the memory-mapped fakes train
    exactly as the same data held in memory."""
    torch = pytest.importorskip("torch", reason="the refiner extra (torch) is not installed")
    from gesturedb.refiner.train import TrainConfig, Trainer

    cached = D.make_training_data(scott_db, seed=2, stride=10, cache=tmp_path / "c.h5")
    cfg = TrainConfig(batch=4, width=8, n_critic=2, seed=5)
    a, b = Trainer(serial, cfg, "id", {}), Trainer(cached, cfg, "id", {})
    for _ in range(2):
        np.testing.assert_equal(a.step(), b.step())  # a NaN ratio (no L1 gradient yet) equals NaN
    for k, v in a.G.state_dict().items():
        assert torch.equal(v, b.G.state_dict()[k]), k


def test_a_worker_refuses_another_copy_of_the_database(scott_db, serial):
    """On Dask the workers open the database by the client's path, which on another machine
    may be another file: the task checks the identity the client sent before assembling."""
    frame_maps = serial.starts[:2, None] + np.arange(64)
    seams = [np.array([0, 8])] * 2
    task = (os.path.abspath(scott_db.path), D.database_identity(scott_db), frame_maps, seams, serial.joints)
    np.testing.assert_array_equal(D._assemble_task(task),
                                  D.assemble_windows(scott_db, frame_maps, seams, serial.joints))
    with pytest.raises(D.InputFileError) as err:
        D._assemble_task((task[0], "0" * 16, *task[2:]))
    msg = str(err.value)
    assert msg.startswith(f"{task[0]}: on Dask worker (not a worker): expected the database the client opened "
                          f"(identity 0000000000000000), got another one ({scott_db.n_frames} frames, identity "
                          f"{task[1]})"), msg


def test_training_data_on_workers_started_by_hand(scott_db, serial, hand_started_workers):
    """The self-search and the assembly on `dask worker` processes running in a folder of their
    own (they open the database by its absolute path): the data made in this process."""
    import distributed

    address, _ = hand_started_workers
    with distributed.Client(address) as client:
        _same(serial, D.make_training_data(scott_db, seed=2, stride=10, scheduler=client))
        # checking the database's identity read the features' widths, not the pose features
        loaded = client.run(lambda: sorted({k for db in D._OPEN.values() for k in vars(db)} & {"pose_features",
                                                                                             "local_rotations"}))
    assert sorted(loaded.values()) == [["local_rotations"]] * 2, loaded
