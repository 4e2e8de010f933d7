"""`gesturedb shard`: shard files of whole recordings + an index file that reads like the database."""
from __future__ import annotations

import mmap
import os
import shutil

import h5py
import numpy as np
import pytest

import gesturedb
from gesturedb.db import schema, shardfiles
from gesturedb.db.database import Database
from gesturedb.db.shardfiles import plan_shards, shard_database
from gesturedb.errors import ParameterError, SchemaError

STEM = "2_scott_0_1_1"


@pytest.fixture(scope="module")
def four_recordings(scott_dir, tmp_path_factory) -> str:
    """The real take under two names, mirrored: 4 recordings (enough for 2 and 3 shards)."""
    src = tmp_path_factory.mktemp("rec")
    for name in ("2_scott_0_1_1", "2_scott_0_9_9"):
        for ext in (".npz", ".wav", ".TextGrid"):
            os.symlink(scott_dir / f"{STEM}{ext}", src / f"{name}{ext}")
    out = tmp_path_factory.mktemp("db") / "four.h5"
    gesturedb.build([src], out, mirror=True).close()
    return str(out)


@pytest.fixture()
def db_copy(four_recordings, tmp_path) -> str:
    p = tmp_path / "four.h5"
    shutil.copyfile(four_recordings, p)
    return str(p)


def _datasets(h5) -> dict:
    out = {}
    h5.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def _same_file_contents(a: str, b: str) -> None:
    with h5py.File(a, "r") as x, h5py.File(b, "r") as y:
        dx, dy = _datasets(x), _datasets(y)
        assert sorted(dx) == sorted(dy)
        for k in dx:
            assert np.array_equal(dx[k], dy[k]), k
        assert {k: v for k, v in x.attrs.items()} == {k: v for k, v in y.attrs.items()
                                                       if k != schema.SHARDS_ATTR}


@pytest.mark.parametrize("n", [1, 2, 3, 7])
def test_plan_covers_recordings_in_order_and_balances_frames(n):
    rng = np.random.default_rng(n)
    for _ in range(50):
        frames = rng.integers(1, 1000, size=int(rng.integers(n, 30)))
        ranges = plan_shards(frames, n)
        assert len(ranges) == n and ranges[0][0] == 0 and ranges[-1][1] == len(frames)
        assert all(a < b for a, b in ranges) and all(ranges[i][1] == ranges[i + 1][0] for i in range(n - 1))
        sizes = [frames[a:b].sum() for a, b in ranges]
        # each cut is the recording boundary nearest its ideal place (when there is room for the rest)
        assert max(sizes) <= frames.sum() / n + 2 * frames.max() or len(frames) < 2 * n


def test_plan_refuses_more_parts_than_recordings():
    with pytest.raises(ParameterError, match="parts: expected an int from 1 to 2 .*whole recordings.*got 3"):
        plan_shards([10, 20], 3)


@pytest.mark.parametrize("parts", [1, 3])
def test_index_reads_exactly_like_the_database(db_copy, parts):
    rep = shard_database(db_copy, parts)
    assert rep.index == db_copy[:-3] + ".index.h5" and len(rep.shards) == parts
    _same_file_contents(db_copy, rep.index)
    with gesturedb.open(db_copy) as a, gesturedb.open(rep.index) as b:
        starts = [r.start_frame for r in a.recordings] + [a.n_frames]
        for (f0, f1), (r0, r1) in zip(rep.frames, rep.recordings):
            assert (f0, f1) == (starts[r0], starts[r1])  # whole recordings
        assert [e["frames"] for e in b.shard_entries] == [tuple(f) for f in rep.frames]
        with h5py.File(rep.index, "r") as h5:
            assert all(h5[p].is_virtual for p in schema.SHARDED_FIELDS)
    # the frames live in the shards: the index is small
    assert os.path.getsize(rep.index) < 0.1 * os.path.getsize(db_copy)
    assert sorted(os.listdir(os.path.dirname(db_copy))) == sorted(
        ["four.h5", os.path.basename(rep.index)] + [os.path.basename(s) for s in rep.shards])  # no lock file left


def test_synth_on_the_index_writes_the_same_bvh(db_copy, scott_dir, tmp_path):
    from gesturedb.cli.main import main

    rep = shard_database(db_copy, 2)
    speech = str(scott_dir / "inputs/2_scott_0_3_3.wav")
    a, b = tmp_path / "a.bvh", tmp_path / "b.bvh"
    assert main(["synth", db_copy, "--audio", speech, "-o", str(a)]) == 0
    assert main(["synth", rep.index, "--audio", speech, "-o", str(b)]) == 0
    assert a.read_bytes() == b.read_bytes()


def test_a_lost_worker_reads_its_shard_file_again_elsewhere(db_copy, scott_dir):
    """The worker holding a shard file's rows killed during a synthesis over an index: a live
    worker reads that file again (the client sends no rows) and the synthesis is the one of a
    single process."""
    import os
    import signal

    import distributed

    from gesturedb.db.cluster import local_cluster
    from gesturedb.synth import Searcher

    rep = shard_database(db_copy, 2)
    speech = scott_dir / "inputs/2_scott_0_2_2.wav"
    with gesturedb.open(db_copy) as one, gesturedb.open(rep.index) as idx, \
            local_cluster(2, memory_limit=0) as cluster, distributed.Client(cluster) as client:
        want = Searcher(one).synthesize(speech, smooth=False)
        s = Searcher(idx, client=client)
        np.testing.assert_array_equal(s.synthesize(speech, smooth=False).positions, want.positions)
        f = s._sharded.shards[0]
        dead = client.who_has(f)[f.key][0]
        os.kill(client.run(os.getpid, workers=[dead])[dead], signal.SIGKILL)
        with distributed.get_task_stream(client) as stream:
            got = s.synthesize(speech, smooth=False)
        np.testing.assert_array_equal(got.positions, want.positions)
        loads = [t for t in stream.data if t["key"].startswith("_load_shard")]
        assert len(loads) == 1 and loads[0]["worker"] != dead, stream.data
        assert not [t for t in stream.data if t["key"].startswith("_make_shard")]


def test_workers_read_their_own_shard_files(db_copy, scott_dir, dask_client, monkeypatch):
    from gesturedb.db.shards import ShardedSearch
    from gesturedb.synth import Searcher

    rep = shard_database(db_copy, 3)
    speech = scott_dir / "inputs/2_scott_0_2_2.wav"
    built = []
    real = ShardedSearch.from_shard_files.__func__
    monkeypatch.setattr(ShardedSearch, "from_shard_files",
                        classmethod(lambda cls, *a, **k: built.append(a[0]) or real(cls, *a, **k)))
    with gesturedb.open(db_copy) as one, gesturedb.open(rep.index) as idx:
        want = Searcher(one).synthesize(speech, k=2, smooth=False)
        s = Searcher(idx, client=dask_client)
        got = s.synthesize(speech, k=2, smooth=False)
        assert len(built) == 1 and [e["file"] for e in built[0]] == rep.shards
        # what each worker holds is its shard file's rows (it was given the file name, not the arrays)
        assert [tuple(f) for f in s._sharded.frame_ranges] == [tuple(f) for f in rep.frames]
        for shard, path in zip(dask_client.gather(s._sharded.shards), rep.shards):
            with h5py.File(path, "r") as h5:
                np.testing.assert_array_equal(shard.pose, h5["frames/pose_features"][()])
        # the client held none of the per-frame arrays: it read the initial pose,
        # the chosen windows and the placement's root rows from the shard files
        assert not set(vars(idx)) & set(Database.FRAME_ARRAYS), sorted(vars(idx))
        mean_one = Searcher(one).synthesize(speech, k=2, smooth=False, init="mean")
        mean_idx = s.synthesize(speech, k=2, smooth=False, init="mean")
        # a control reads the features and saved masks its expressions name, not all of them
        ctl = "0-20: left_wrist_height > p85; 20-: symmetric"
        ctl_one = Searcher(one).synthesize(speech, smooth=False, control=ctl)
        ctl_idx = s.synthesize(speech, smooth=False, control=ctl)
        held = set(vars(idx))
        assert not held & (set(Database.FRAME_ARRAYS) | {"controls", "masks"}), sorted(held)
        s._sharded.close()
    assert want.steps == got.steps
    np.testing.assert_array_equal(want.positions, got.positions)
    assert mean_one.steps == mean_idx.steps and mean_one.steps != want.steps
    np.testing.assert_array_equal(mean_one.positions, mean_idx.positions)
    assert ctl_one.steps == ctl_idx.steps and ctl_one.steps[0]["control"] == "left_wrist_height > p85"
    np.testing.assert_array_equal(ctl_one.positions, ctl_idx.positions)


@pytest.mark.parametrize("how", ["read", "mapped", "sharded"])
def test_rows_and_means_are_the_arrays_without_loading_them(db_copy, how):
    """Database.rows / frame_mean read from the file (through an index: from its
    shard files; a contiguous dataset: from its memory map, which reads only the
    rows indexed) exactly what indexing the loaded arrays gives."""
    path = shard_database(db_copy, 3).index if how == "sharded" else db_copy
    rng = np.random.default_rng(4)
    with gesturedb.open(path) as lazy, gesturedb.open(db_copy) as full:
        lazy.map_frames = how == "mapped"
        full.map_frames = False
        F = full.n_frames
        # runs across recordings and shard boundaries, any order, repeats, one frame, none
        picks = [rng.integers(0, F, 40), np.arange(F), np.r_[np.arange(F - 9, F), np.arange(5)][::-1],
                 np.array([F // 2, F // 2, 0]), np.array([F - 1]), np.zeros(0, np.int64)]
        for name in Database.FRAME_ARRAYS:
            arr = getattr(full, name)
            for frames in picks:
                got = lazy.rows(name, frames)
                assert got.dtype == arr.dtype and got.shape == (frames.size,) + arr.shape[1:]
                np.testing.assert_array_equal(got, arr[frames], err_msg=name)
            assert (name in vars(lazy)) == (how == "mapped")
            if how == "mapped":
                assert isinstance(vars(lazy)[name].base.base.obj, mmap.mmap)  # the map, not a read
        for col in (0, 7, -1):
            np.testing.assert_array_equal(lazy.rows("local_rotations", picks[0], column=col),
                                          full.local_rotations[picks[0], col])
            np.testing.assert_array_equal(full.rows("local_rotations", picks[0], column=col),  # the loaded path
                                          full.local_rotations[picks[0], col])
        for name in ("pose_features", "local_rotations"):
            want = getattr(full, name).mean(axis=0, dtype=np.float64)
            for chunk in (1, 7, 16384):
                assert np.array_equal(lazy.frame_mean(name, chunk=chunk, stored=False), want), (name, chunk)
            assert np.array_equal(full.frame_mean(name, chunk=100, stored=False), want)
            assert np.array_equal(lazy.frame_mean(name), want)  # pose_features: the stored mean
        assert not set(vars(lazy)) & set(Database.FRAME_ARRAYS) or how == "mapped"
        with pytest.raises(ParameterError, match=rf"frames: expected indices in 0..{F - 1} .*got {F}"):
            lazy.rows("pose_features", [0, F])
        with pytest.raises(ParameterError, match=r"frames: expected indices .*got -1"):
            lazy.rows("pose_features", [-1])
        with pytest.raises(ParameterError, match=r"frames: expected a 1-D array of frame indices.*float"):
            lazy.rows("pose_features", [0.5])
        with pytest.raises(ParameterError, match=r"name: expected one of .*pose_features.*got 'poses'"):
            lazy.rows("poses", [0])
        with pytest.raises(ParameterError, match=r"column: expected an index of the second axis of "
                                                 r"root_positions .*got 3"):
            lazy.rows("root_positions", [0], column=3)


def test_the_stored_pose_mean_is_numpys_and_reads_no_frames(db_copy, tmp_path):
    """build writes the pose features' mean beside them, sharding keeps it on the index
    (not on the shards, which hold a part), and frame_mean reads it without touching a
    frame; a file without it is read through, and a bad one is a SchemaError."""
    rep = shard_database(db_copy, 2)
    with gesturedb.open(db_copy) as full:
        want = full.pose_features.mean(axis=0, dtype=np.float64)
    with h5py.File(db_copy, "r") as h5:
        assert np.array_equal(h5["frames/pose_features"].attrs["mean"], want)
    for path in rep.shards:
        with h5py.File(path, "r") as h5:
            assert "mean" not in h5["frames/pose_features"].attrs
    # through the index: the attribute alone, no frame read
    class NoRows:
        def __init__(self, ds):
            self.ds, self.shape, self.ndim, self.dtype = ds, ds.shape, ds.ndim, ds.dtype

        def __getitem__(self, key):
            raise AssertionError(f"read frames {key}")

    with gesturedb.open(rep.index) as idx:
        real = idx._frame_dataset
        idx._frame_dataset = lambda name: NoRows(real(name))
        assert np.array_equal(idx.frame_mean("pose_features"), want)
        with pytest.raises(AssertionError, match="read frames"):
            idx.frame_mean("pose_features", stored=False)
    # a file written before the attribute: the chunked pass, the same bits
    with h5py.File(db_copy, "r+") as h5:
        del h5["frames/pose_features"].attrs["mean"]
    with gesturedb.open(db_copy) as old:
        assert np.array_equal(old.frame_mean("pose_features", chunk=333), want)
    n = want.size
    for bad, match in ((want[:-1], rf"expected float64 of shape \({n},\), got float64 of shape \({n - 1},\)"),
                       (want.astype(np.float32), rf"expected float64 of shape \({n},\), got float32"),
                       (np.where(np.arange(want.size) == 3, np.nan, want), r"expected finite values, got nan")):
        with h5py.File(db_copy, "r+") as h5:
            h5["frames/pose_features"].attrs["mean"] = bad
        with pytest.raises(SchemaError, match=rf"{os.path.basename(db_copy)}.*frames/pose_features attribute "
                                              rf"'mean': {match}"):
            gesturedb.open(db_copy)


def test_placement_read_per_recording_is_the_whole_arrays_placement(db_copy):
    """recording_placement reads one recording's root rows at a time; its sums are those
    of one bincount over all frames (the code before it), bit for bit."""
    from gesturedb.synth.assemble import _yaw_of, recording_placement

    rep = shard_database(db_copy, 2)
    with gesturedb.open(rep.index) as idx, gesturedb.open(db_copy) as db:
        mean_yaw, centre = recording_placement(idx)
        assert not set(vars(idx)) & set(Database.FRAME_ARRAYS)
        rec = db.frame_recording
        yaw = _yaw_of(np.asarray(db.local_rotations[:, 0], dtype=np.float64))
        root = np.asarray(db.root_positions, dtype=np.float64)
        n = len(db.recordings)
        want_yaw = np.arctan2(np.bincount(rec, np.sin(yaw), n), np.bincount(rec, np.cos(yaw), n))
        want = np.stack([np.bincount(rec, root[:, 0], n), np.zeros(n), np.bincount(rec, root[:, 2], n)], 1)
        want /= np.maximum(np.bincount(rec, minlength=n), 1)[:, None]
        assert n == 4 and np.array_equal(mean_yaw, want_yaw) and np.array_equal(centre, want)


def test_the_set_moves_together(db_copy, tmp_path):
    rep = shard_database(db_copy, 2)
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    for f in [rep.index, *rep.shards]:
        shutil.move(f, moved / os.path.basename(f))
    with gesturedb.open(db_copy) as a, gesturedb.open(moved / os.path.basename(rep.index)) as b:
        np.testing.assert_array_equal(a.local_rotations, b.local_rotations)


def test_a_missing_or_foreign_shard_is_a_clear_error(db_copy, tmp_path):
    rep = shard_database(db_copy, 2)
    with pytest.raises(SchemaError, match=r"this is part 2 of 2 of a sharded database.*four.index.h5"):
        gesturedb.open(rep.shards[1])
    # a shard of another sharding (same place in the set, other token) is refused, not read
    other = shard_database(db_copy, 2, index=str(tmp_path / "other.h5"))
    shutil.copyfile(other.shards[0], rep.shards[0])
    with pytest.raises(SchemaError, match=r"shards\[0\] .*expected the shard .*another sharding"):
        gesturedb.open(rep.index)
    os.unlink(rep.shards[0])
    with pytest.raises(SchemaError) as err:
        gesturedb.open(rep.index)
    assert str(err.value).startswith(f"{rep.index}: shards[0]") and "is missing" in str(err.value)


def test_a_worker_refuses_a_stale_copy_of_a_shard(db_copy, scott_dir, tmp_path, dask_client):
    """The client checks the folder when it opens the index, but a worker on another machine
    reads its own copy: that copy, if stale (another sharding's file at the same path), is
    refused on the worker with the file and the worker named, not searched."""
    from gesturedb.synth import Searcher

    rep = shard_database(db_copy, 2)
    other = shard_database(db_copy, 2, index=str(tmp_path / "other.h5"))
    speech = scott_dir / "inputs/2_scott_0_2_2.wav"
    with gesturedb.open(rep.index) as idx:  # the client's check passes here
        # what the worker will see: another file at the path (the client holds the shard it checked open)
        shutil.copyfile(other.shards[1], str(tmp_path / "stale.h5"))
        os.replace(tmp_path / "stale.h5", rep.shards[1])
        with pytest.raises(SchemaError) as err:
            Searcher(idx, client=dask_client).synthesize(speech, smooth=False)
    msg = str(err.value)
    assert msg.startswith(f"{rep.shards[1]}: on Dask worker ") and "expected the shard" in msg
    assert "'part': 2" in msg and "same paths as the client" in msg, msg


def test_load_shard_checks_the_file_it_is_given(db_copy):
    """The worker-side check alone: the file's part, token and frames, its feature widths, a
    missing file; the shard it expects is read."""
    from gesturedb.db.shards import _load_shard

    rep = shard_database(db_copy, 2)
    with gesturedb.open(rep.index) as idx:
        entries = idx.shard_entries
        Dp, Da = idx.h5["frames/pose_features"].shape[1], idx.h5["frames/audio_features"].shape[1]
    (f0, f1), path = entries[0]["frames"], entries[0]["file"]
    want = schema.shard_expected(entries, 0)
    seg = (np.array([0], np.int64), np.array([f1 - f0], np.int64))
    shard = _load_shard(path, want, f1 - f0, Dp, Da, *seg, False)
    with h5py.File(path, "r") as h5:
        np.testing.assert_array_equal(shard.pose, h5["frames/pose_features"][()])
    cases = [((path, schema.shard_expected(entries, 1), entries[1]["frames"][1] - entries[1]["frames"][0], Dp, Da),
              "expected the shard .*'part': 2.* got .*'part': 1"),
             ((path, {**want, "token": "x"}, f1 - f0, Dp, Da), "expected the shard .*'token': 'x'"),
             ((path, want, f1 - f0, Dp + 1, Da),
              rf"frames/pose_features: expected shape \({f1 - f0}, {Dp + 1}\), got \({f1 - f0}, {Dp}\)"),
             ((path, want, f1 - f0, Dp, Da - 1), r"frames/audio_features: expected shape"),
             ((path + ".gone", want, f1 - f0, Dp, Da), r"is missing")]
    for args, pattern in cases:
        with pytest.raises(SchemaError, match=pattern) as err:
            _load_shard(*args, *seg, False)
        assert str(err.value).startswith(f"{args[0]}: on Dask worker (not a worker): ")


def test_cli_shard_and_one_line_errors(db_copy, capsys):
    from gesturedb.cli.main import main

    assert main(["shard", db_copy, "--parts", "2", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "index of 2 shard(s)" in out and "recordings 0..1" in out and "recordings 2..3" in out
    assert main(["info", db_copy[:-3] + ".index.h5"]) == 0
    assert "shards       2 file(s) beside this index" in capsys.readouterr().out
    assert main(["shard", db_copy, "--parts", "5", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "parts: expected an int from 1 to 4" in err and "got 5" in err


def test_resharding_in_place_replaces_the_old_shards(db_copy):
    first = shard_database(db_copy, 3, index=db_copy)  # the database itself becomes an index
    assert first.index == db_copy and all(os.path.isfile(s) for s in first.shards)
    second = shard_database(db_copy, 2, index=db_copy)
    assert sorted(second.removed) == sorted(first.shards)
    assert not any(os.path.exists(s) for s in first.shards)
    with gesturedb.open(db_copy) as db:
        assert [e["file"] for e in db.shard_entries] == second.shards


def test_an_interrupted_sharding_leaves_the_previous_set(db_copy, monkeypatch):
    first = shard_database(db_copy, 2)
    before = sorted(os.listdir(os.path.dirname(db_copy)))
    index_bytes = open(first.index, "rb").read()

    def stop(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(shardfiles, "_fill_index", stop)
    with pytest.raises(KeyboardInterrupt):
        shard_database(db_copy, 3)
    assert sorted(os.listdir(os.path.dirname(db_copy))) == before
    assert open(first.index, "rb").read() == index_bytes
    with gesturedb.open(first.index) as db:
        assert len(db.shard_entries) == 2


def test_edits_keep_the_index_an_index(db_copy):
    from gesturedb.cli.main import main

    rep = shard_database(db_copy, 2)
    assert main(["masks", rep.index, "add", "calm", "left_wrist_speed < p50"]) == 0
    assert main(["keywords", rep.index, "add", "time"]) == 0
    with gesturedb.open(rep.index) as db, h5py.File(rep.index, "r") as h5:
        assert "calm" in db.masks and len(db.shard_entries) == 2
        assert all(h5[p].is_virtual for p in schema.SHARDED_FIELDS)


def test_refiner_training_data_over_shards_is_the_local_data(db_copy, dask_client):
    """The refiner's self-search (every training window's own audio, its neighbourhood
    excluded, per-window k) over a single file cut into 3 shards (in chunks of 50
    windows) and over an index's 2 shard files, with the windows assembled on the
    Dask workers, gives exactly the training data of this process."""
    from gesturedb.refiner.data import make_training_data

    with gesturedb.open(db_copy) as db:
        local = make_training_data(db, seed=3, stride=20)  # every 4th window: the assembly is the slow part
        calls = []
        cut = make_training_data(db, seed=3, stride=20, scheduler=dask_client, parts=3, chunk=50,
                                 progress=lambda *a: calls.append(a))
    rep = shard_database(db_copy, 2)
    with gesturedb.open(rep.index) as idx:
        files = make_training_data(idx, seed=3, stride=20, scheduler=dask_client)
    W = local.n_windows
    assert W > 150 and (local.ks > 1).any()
    # searched 50 windows at a time, then assembled 32 at a time (in whatever order the workers finish)
    assert [c for c in calls if c[0] == "search"] == [("search", min(b, W), W) for b in range(50, W + 50, 50)]
    done = [c[1] for c in calls if c[0] == "assembly"]
    assert len(done) == -(-W // 32) and done[-1] == W and done == sorted(done)
    every = np.arange(W)
    for other in (cut, files):
        for name in ("frame_audio", "frame_real", "starts", "ks", "joints"):
            np.testing.assert_array_equal(getattr(other, name), getattr(local, name), err_msg=name)
        np.testing.assert_array_equal(other.fake(every), local.fake(every), err_msg="knn")

def test_cli_synth_on_workers_started_by_hand(db_copy, scott_dir, tmp_path, capsys, hand_started_workers):
    """`gesturedb synth INDEX --scheduler tcp://HOST:PORT` as on machines of one's own (workers
    started by `dask worker` in another folder): each reads its shard file by its absolute path;
    the BVH is the local one byte for byte. A scheduler that does not answer is a one-line error
    and exit 2, with nothing written."""
    import distributed

    from gesturedb.cli.main import main

    address, watch = hand_started_workers
    rep = shard_database(db_copy, 2)
    speech = str(scott_dir / "inputs/2_scott_0_3_3.wav")
    local, remote = tmp_path / "local.bvh", tmp_path / "remote.bvh"
    assert main(["synth", db_copy, "--audio", speech, "-o", str(local)]) == 0
    with distributed.get_task_stream(watch) as stream:
        assert main(["synth", rep.index, "--audio", speech, "-o", str(remote), "--scheduler", address]) == 0
    assert remote.read_bytes() == local.read_bytes()
    # each worker read one shard file
    loads = [t["worker"] for t in stream.data if t["key"].startswith("_load_shard")]
    assert len(loads) == 2 and len(set(loads)) == 2, stream.data
    capsys.readouterr()
    gone = tmp_path / "gone.bvh"
    assert main(["synth", rep.index, "--audio", speech, "-o", str(gone), "--scheduler", "tcp://127.0.0.1:1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "scheduler: expected a reachable Dask scheduler at tcp://127.0.0.1:1" in err
    assert not gone.exists()


# ---------------------------------------------------------------- issue 41: readers during a re-sharding

ROUNDS = 10
JOIN_S = 60.0


def _frames_digest(db) -> dict:
    return {name: getattr(db, name).tobytes() for name in ("local_rotations", "pose_features", "root_positions")}


def test_an_open_index_reads_its_own_shards_after_a_resharding_removed_them(db_copy):
    """Case 3: the reader opened the index, the index was re-sharded in place (old shard files
    removed): the reader still reads the frames it opened, not HDF5's fill values (zeros)."""
    with gesturedb.open(db_copy) as db:
        want = _frames_digest(db)
        frames = np.arange(db.n_frames)[::7]
        want_rows = db.local_rotations[frames].copy()
    first = shard_database(db_copy, 2, index=db_copy)
    with gesturedb.open(db_copy) as idx:
        second = shard_database(db_copy, 3, index=db_copy)
        assert sorted(second.removed) == sorted(first.shards)
        assert not any(os.path.exists(f) for f in first.shards)
        np.testing.assert_array_equal(idx.rows("local_rotations", frames), want_rows)
        np.testing.assert_array_equal(idx.rows("local_rotations", frames, column=0), want_rows[:, 0])
        assert idx.frame_mean("pose_features", stored=False).shape == (idx.pose_features.shape[1],)
        assert _frames_digest(idx) == want
        motion = idx.motion(idx.recordings[-1].name)  # what `gesturedb export` refused as "norm 0"
        np.testing.assert_allclose(np.linalg.norm(motion.rotations, axis=-1), 1.0, atol=1e-5)


def _read_while_resharding(index, want, barrier, done, queue):
    try:
        barrier.wait(JOIN_S)
        reads = 0
        while not done.is_set() or reads < 2:
            with gesturedb.open(index) as db:
                if _frames_digest(db) != want:
                    queue.put(("wrong", f"read {reads}: frames differ (zeros: "
                                        f"{not np.any(db.local_rotations)})"))
                    return
            reads += 1
        queue.put(("ok", reads))
    except BaseException as exc:
        queue.put(("error", f"{type(exc).__name__}: {exc}"))


def _reshard(index, parts, barrier, done, queue):
    try:
        barrier.wait(JOIN_S)
        for n in parts:
            shard_database(index, n, index=index)
        queue.put(("ok", 0))
    except BaseException as exc:
        queue.put(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        done.set()


def test_readers_racing_a_resharding_read_the_database_every_time(db_copy):
    """Case 3 as a race: readers open and read the index over and over while it is re-sharded in
    in another process; every read is the database (no zeros, no error)."""
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    with gesturedb.open(db_copy) as db:
        want = _frames_digest(db)
    shard_database(db_copy, 2, index=db_copy)
    total = 0
    for r in range(ROUNDS):
        barrier, done, queue = ctx.Barrier(2), ctx.Event(), ctx.Queue()
        procs = [ctx.Process(target=_read_while_resharding, args=(db_copy, want, barrier, done, queue)),
                 ctx.Process(target=_reshard, args=(db_copy, (3 - r % 2,), barrier, done, queue))]
        for p in procs:
            p.start()
        out = [queue.get(timeout=JOIN_S) for _ in procs]
        for p in procs:
            p.join(JOIN_S)
            assert not p.is_alive(), "a reader or the re-sharding hung"
        assert all(state == "ok" for state, _ in out), out
        total += sum(n for state, n in out)
    assert total >= 2 * ROUNDS
    with gesturedb.open(db_copy) as db:
        assert _frames_digest(db) == want and len(db.shard_entries) == 2
    left = [f for f in os.listdir(os.path.dirname(db_copy)) if f.endswith(".h5")]
    assert len(left) == 3, left  # the index and its two shards: every older shard was removed


def test_concurrent_reshardings_and_an_edit_lose_nothing(db_copy):
    """Two re-shardings of one index and a mask edit of it at once: the edit survives (the
    sharding holds the index's lock while it copies), and no shard file is left behind."""
    import multiprocessing

    from gesturedb.db import edit as dbedit

    ctx = multiprocessing.get_context("fork")
    shard_database(db_copy, 2, index=db_copy)

    def run(fn, barrier, queue):
        try:
            barrier.wait(JOIN_S)
            fn()
            queue.put(("ok", None))
        except BaseException as exc:
            queue.put(("error", f"{type(exc).__name__}: {exc}"))

    for i in range(ROUNDS):
        barrier, queue = ctx.Barrier(3), ctx.Queue()
        fns = [lambda: shard_database(db_copy, 3, index=db_copy), lambda: shard_database(db_copy, 2, index=db_copy),
               lambda i=i: dbedit.save_mask(db_copy, f"m{i}", "left_wrist_speed < p50")]
        procs = [ctx.Process(target=run, args=(fn, barrier, queue)) for fn in fns]
        for p in procs:
            p.start()
        out = [queue.get(timeout=JOIN_S) for _ in procs]
        for p in procs:
            p.join(JOIN_S)
            assert not p.is_alive(), "a sharding or an edit hung"
        assert all(state == "ok" for state, _ in out), out
        with gesturedb.open(db_copy) as db:
            assert {f"m{k}" for k in range(i + 1)} <= set(db.masks)
            shards = {e["file"] for e in db.shard_entries}
        on_disk = {os.path.join(os.path.dirname(db_copy), f) for f in os.listdir(os.path.dirname(db_copy))
                   if f.endswith(".h5") and f != os.path.basename(db_copy)}
        assert on_disk == shards


# ---------------------------------------------------------------- issue 41: the mappings that are read

def _remap(index: str, path: str, files: list[str]) -> None:
    """Point the virtual dataset ``path`` of an index at ``files`` (one per shard), leaving its shards list."""
    with h5py.File(index, "r+") as h5:
        old = h5[path]
        shape, dtype, attrs = old.shape, old.dtype, dict(old.attrs)
        entries = schema.shard_entries(h5, index)
        del h5[path]
        layout = h5py.VirtualLayout(shape=shape, dtype=dtype)
        for f, e in zip(files, entries):
            a, b = e["frames"]
            layout[a:b] = h5py.VirtualSource(f, path, shape=(b - a,) + shape[1:])
        ds = h5.create_virtual_dataset(path, layout, fillvalue=None)
        for k, v in attrs.items():
            ds.attrs[k] = v


def test_the_virtual_dataset_mappings_themselves_are_checked(db_copy, tmp_path, capsys):
    """Case 4: the shards list is right but a mapping reads another file: refused, naming the
    dataset and the mapping, instead of synthesizing from the other file with exit 0."""
    from gesturedb.cli.main import main

    rep = shard_database(db_copy, 2)
    other = shard_database(db_copy, 2, index=str(tmp_path / "other.h5"))
    assert os.path.dirname(other.shards[0]) == os.path.dirname(rep.index)  # another sharding's files, beside it
    _remap(rep.index, "frames/local_rotations", [os.path.basename(f) for f in other.shards])
    want0 = os.path.basename(rep.shards[0])
    got0 = os.path.basename(other.shards[0])
    with pytest.raises(SchemaError, match=rf"frames/local_rotations: mapping 0: expected {want0}:frames/local_rotations "
                                          rf"\(shard 1 of the index's list\), got {got0}:frames/local_rotations"):
        gesturedb.open(rep.index)
    _remap(rep.index, "frames/local_rotations", ["/etc/passwd", os.path.basename(rep.shards[1])])
    with pytest.raises(SchemaError, match=r"frames/local_rotations: mapping 0: expected .*got /etc/passwd:"):
        gesturedb.open(rep.index)
    assert main(["info", rep.index]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err and "/etc/passwd" in err and rep.index in err
    # a mapping onto the wrong rows of the right file
    _remap(rep.index, "frames/local_rotations", [os.path.basename(f) for f in reversed(rep.shards)])
    with pytest.raises(SchemaError, match=r"frames/local_rotations: mapping 0: expected .*1-of-2\.h5.*got .*2-of-2"):
        gesturedb.open(rep.index)
    # the data stored in the index itself instead of its shards
    with h5py.File(rep.index, "r+") as h5:
        del h5["frames/local_rotations"]
        h5.create_dataset("frames/local_rotations", data=np.zeros((1, 1, 4), dtype=np.float32))
    with pytest.raises(SchemaError, match=r"frames/local_rotations: expected a virtual dataset over the 2 shard"):
        gesturedb.open(rep.index)


def test_upgrading_a_sharded_index_of_an_older_schema_says_how(db_copy):
    """An index's frames are in its shards: `gesturedb upgrade` refuses it with what to do instead, and
    leaves every file as it was."""
    from gesturedb.db.upgrade import upgrade

    rep = shard_database(db_copy, 2)
    for f in (rep.index, *rep.shards):
        with h5py.File(f, "r+") as h5:
            h5.attrs["schema_version"] = 3
    before = {f: open(f, "rb").read() for f in (rep.index, *rep.shards)}
    with pytest.raises(SchemaError, match=r"index of a sharded database of schema 3; upgrade the single database "
                                          r"it was sharded from .*gesturedb shard"):
        upgrade(rep.index)
    assert {f: open(f, "rb").read() for f in before} == before
