"""Per-frame arrays memory-mapped from contiguous datasets; read where they are chunked, filtered or virtual."""
from __future__ import annotations

import mmap
import os
import shutil

import h5py
import numpy as np
import pytest

import gesturedb
from gesturedb.db import edit, schema, storage
from gesturedb.db.database import Database, mappable
from gesturedb.db.shardfiles import shard_database

NAMES = list(Database.FRAME_ARRAYS)


def _is_mapped(a: np.ndarray) -> bool:
    b = a
    while b is not None:
        if isinstance(b, mmap.mmap):
            return True
        b = getattr(b, "base", None) if not isinstance(b, memoryview) else b.obj
    return False


def _stored(path, name: str) -> np.ndarray:
    with h5py.File(path, "r") as h5:
        return h5[Database.FRAME_ARRAYS[name]][()]


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _rewrite_frames(src, dst, **create) -> None:
    """A copy of ``src`` whose per-frame arrays are stored with ``create`` (chunks=..., compression=...)."""
    shutil.copyfile(src, dst)
    with h5py.File(dst, "r+") as h5:
        for p in schema.CONTIGUOUS_FIELDS:
            data, attrs = h5[p][()], dict(h5[p].attrs)
            del h5[p]
            d = h5.create_dataset(p, data=data, **create)
            for k, v in attrs.items():
                d.attrs[k] = v


@pytest.fixture()
def db_copy(scott_db_path, tmp_path) -> str:
    p = tmp_path / "scott.h5"
    shutil.copyfile(scott_db_path, p)
    return str(p)


def test_a_build_stores_the_frames_contiguous_and_open_maps_them_bit_for_bit(scott_db_path, monkeypatch):
    with h5py.File(scott_db_path, "r") as h5:
        for p in schema.CONTIGUOUS_FIELDS:
            assert h5[p].chunks is None and mappable(h5[p]), p
    with gesturedb.open(scott_db_path) as db:
        mapped = {n: getattr(db, n) for n in NAMES}
    monkeypatch.setenv("GESTUREDB_MMAP", "0")
    with gesturedb.open(scott_db_path) as db:
        read = {n: getattr(db, n) for n in NAMES}
    for n in NAMES:
        a, b = mapped[n], read[n]
        assert _is_mapped(a) and not _is_mapped(b), n
        assert not a.flags.writeable and a.flags.c_contiguous, n
        assert _same_bits(a, b) and _same_bits(a, _stored(scott_db_path, n)), n
        with pytest.raises(ValueError, match="read-only"):
            a[0] = 0
    # the arrays outlive the database they came from (the map holds its own descriptor)
    assert float(np.sum(mapped["pose_features"], dtype=np.float64)) == float(np.sum(read["pose_features"],
                                                                                    dtype=np.float64))


@pytest.mark.parametrize("layout", [{"chunks": True}, {"compression": "gzip"}, {"chunks": True, "shuffle": True}])
def test_chunked_or_filtered_frames_are_read_and_compacted_by_the_next_edit(scott_db_path, tmp_path, layout):
    old = tmp_path / "old.h5"
    _rewrite_frames(scott_db_path, old, **layout)
    with gesturedb.open(old) as db:
        for n in NAMES:
            a = getattr(db, n)
            assert not _is_mapped(a) and not a.flags.writeable, n
            assert _same_bits(a, _stored(scott_db_path, n)), n
    edit.save_mask(old, "calm", "hand_speed < 0.3")
    filtered = "compression" in layout or "shuffle" in layout
    with h5py.File(old, "r") as h5:
        for p in schema.CONTIGUOUS_FIELDS:
            # an edit stores unfiltered chunked arrays contiguous; a filtered one stays as it is
            assert (h5[p].chunks is None) != filtered, p
    with gesturedb.open(old) as db:
        assert "calm" in db.masks
        for n in NAMES:
            a = getattr(db, n)
            assert _is_mapped(a) != filtered, n
            assert _same_bits(a, _stored(scott_db_path, n)), n


def test_compact_copy_keeps_every_dataset_and_attribute(scott_db_path, tmp_path):
    chunked, out = tmp_path / "chunked.h5", tmp_path / "out.h5"
    _rewrite_frames(scott_db_path, chunked, chunks=True)
    storage.compact_copy(str(chunked), str(out), contiguous=schema.CONTIGUOUS_FIELDS)

    def everything(path):
        items = {}

        def visit(name, obj):
            items[name] = ({k: (v, obj.attrs.get_id(k).dtype) for k, v in obj.attrs.items()},
                           obj[()].tobytes() if isinstance(obj, h5py.Dataset) and obj.dtype.kind != "O"
                           else obj[()].tolist() if isinstance(obj, h5py.Dataset) else None)
        with h5py.File(path, "r") as h5:
            h5.visititems(visit)
            items[""] = ({k: str(v) for k, v in h5.attrs.items()}, None)
        return items

    a, b = everything(scott_db_path), everything(out)
    assert sorted(a) == sorted(b)
    for k in a:
        assert str(a[k][0]) == str(b[k][0]) and a[k][1] == b[k][1], k
    with h5py.File(out, "r") as h5:
        assert all(h5[p].chunks is None for p in schema.CONTIGUOUS_FIELDS)


def test_an_index_file_reads_its_shards(db_copy):
    rep = shard_database(db_copy, 1)  # one recording: one shard, still virtual datasets in the index
    with gesturedb.open(rep.index) as db:
        for n in NAMES:
            a = getattr(db, n)
            assert not _is_mapped(a), n  # virtual datasets over the shard files: read
            assert _same_bits(a, _stored(db_copy, n)), n


def test_an_edit_after_open_leaves_the_mapped_arrays_as_they_were(db_copy):
    db = gesturedb.open(db_copy)
    pose, rot = db.pose_features, db.local_rotations
    before = pose.copy(), rot.copy()
    ino = os.stat(db_copy).st_ino
    edit.save_mask(db_copy, "calm", "hand_speed < 0.3")  # a new file renamed over the old one
    edit.remove_mask(db_copy, "calm")
    assert os.stat(db_copy).st_ino != ino
    # the open database keeps its file: the mapped arrays and what it reads later are the old inode's
    assert _same_bits(pose, before[0]) and _same_bits(rot, before[1])
    assert _same_bits(db.audio_features, _stored(db_copy, "audio_features"))
    assert _same_bits(db.rows("pose_features", [0, 5, 3]), before[0][[0, 5, 3]])
    db.close()
    assert _same_bits(pose, before[0])  # still readable after close
    h5py.File(db_copy, "r+").close()  # and the map holds no HDF5 lock on the file
    with gesturedb.open(db_copy) as db2:
        assert _is_mapped(db2.pose_features) and _same_bits(db2.pose_features, before[0])


def test_a_file_replaced_under_a_mapping_is_never_mixed_in(db_copy, tmp_path):
    other = tmp_path / "other.h5"
    _rewrite_frames(db_copy, other)  # contiguous again, but elsewhere in the file and zeroed below
    with h5py.File(other, "r+") as h5:
        h5[schema.POSE_FEATURES][...] = 0
    with gesturedb.open(db_copy) as db:
        want = _stored(db_copy, "pose_features")
        os.replace(other, db_copy)
        # mapped after the replacement: the open file (its descriptor), not the name
        assert _is_mapped(db.pose_features) and _same_bits(db.pose_features, want)
