"""The schema module: declared datasets are checked on write, and the README shows the current schema."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from gesturedb.db import schema
from gesturedb.errors import SchemaError


def test_write_checks_dtype_and_shapes_across_datasets(tmp_path):
    with h5py.File(tmp_path / "x.h5", "w") as h5:
        dims: dict = {}
        schema.write(h5, "frames/pose_features", np.zeros((10, 96), np.float32), dims)
        assert dims == {"F": 10, "Dp": 96}
        with pytest.raises(SchemaError, match=r"frames/audio_features: dimension F expected 10 \(from another dataset\), got 11"):
            schema.write(h5, "frames/audio_features", np.zeros((11, 14), np.float32), dims)
        with pytest.raises(SchemaError, match=r"frames/joint_positions: axis 2 expected 3, got 4"):
            schema.write(h5, "frames/joint_positions", np.zeros((10, 5, 4), np.float32), dims)
        with pytest.raises(SchemaError, match=r"chunks/start: expected int64, got float64"):
            schema.write(h5, "chunks/start", np.zeros(3), dims)
        schema.write(h5, "recordings/name", ["a", "b"], dims)
        assert schema.read(h5, "recordings/name") == ["a", "b"]
        assert h5["frames/pose_features"].attrs["unit"] == "m"


def test_every_declared_field_has_unit_doc_and_known_dims():
    known = {"F", "J", "R", "C", "K", "W", "E", "Dp", "Da", "B", "S", "X", "K1", "G", "GL", "P"}
    for f in schema.FIELDS:
        assert f.doc
        assert all(isinstance(d, int) or d in known for d in f.shape), f


@pytest.mark.parametrize("sizes", [[1000], [3, 0, 400, 1, 596], [1] * 50])
def test_row_writer_equals_one_write(tmp_path, sizes):
    """Rows written a block at a time (the build: a recording at a time) give the dataset and the
    stored mean of one write of the whole array, bit for bit, whatever the blocks (a column of
    -0.0 included, where the start of the sum shows)."""
    rng = np.random.default_rng(len(sizes))
    x = (rng.normal(size=(sum(sizes), 96)) * 3).astype(np.float32)
    x[:, 5] = -0.0  # a column of negative zeros: numpy's mean keeps -0.0
    with h5py.File(tmp_path / "one.h5", "w") as h5:
        schema.write(h5, "frames/pose_features", x, {})
        want, want_mean = h5["frames/pose_features"][()], h5["frames/pose_features"].attrs[schema.MEAN_ATTR]
    with h5py.File(tmp_path / "rows.h5", "w") as h5:
        dims: dict = {}
        rows = schema.RowWriter(h5, "frames/pose_features", (96,))
        s0 = 0
        for n in sizes:
            rows.write(x[s0:s0 + n].astype(np.float64) if n == 3 else x[s0:s0 + n])  # converted like write
            s0 += n
        rows.close(dims)
        assert dims == {"F": x.shape[0], "Dp": 96}
        got, got_mean = h5["frames/pose_features"][()], h5["frames/pose_features"].attrs[schema.MEAN_ATTR]
        assert h5["frames/pose_features"].chunks == ((1 << 22) // 384, 96)  # chunks of about 4 MB
    assert got.tobytes() == want.tobytes() and got_mean.tobytes() == want_mean.tobytes()


def test_row_writer_errors_name_the_field_and_the_row(tmp_path):
    with h5py.File(tmp_path / "x.h5", "w") as h5:
        rows = schema.RowWriter(h5, "frames/joint_positions", (5, 3))
        rows.write(np.zeros((4, 5, 3), np.float32))
        bad = np.zeros((4, 5, 3), np.float32)
        bad[2, 1, 0] = np.nan
        with pytest.raises(SchemaError, match=r"frames/joint_positions: expected finite values, got nan at index \(6, 1, 0\)"):
            rows.write(bad)
        with pytest.raises(SchemaError, match=r"frames/joint_positions: expected rows of shape \(5, 3\), "
                                               r"got \(7, 5, 4\) at row 4"):
            rows.write(np.zeros((7, 5, 4), np.float32))
        with pytest.raises(SchemaError, match=r"frames/root_positions: axis 1 expected 3, got 4"):
            schema.RowWriter(h5, "frames/root_positions", (4,))


def test_growing_row_writer_checks_its_rows_against_other_datasets_at_close(tmp_path):
    with h5py.File(tmp_path / "x.h5", "w") as h5:
        dims: dict = {}
        schema.write(h5, "frames/audio_features", np.zeros((5, 14), np.float32), dims)
        rows = schema.RowWriter(h5, "frames/pose_features", (96,), chunk_rows=7)
        assert h5["frames/pose_features"].chunks == (7, 96)  # the build's: its first recording's length
        rows.write(np.zeros((3, 96), np.float32))
        with pytest.raises(SchemaError, match=r"frames/pose_features: dimension F expected 5 \(from another dataset\), got 3"):
            rows.close(dims)
