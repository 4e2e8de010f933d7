"""The schema module: declared datasets are checked on write, and the README shows the current schema."""
from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from gesturedb.db import schema
from gesturedb.errors import SchemaError


def test_readme_schema_table_is_current():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert schema.describe() in readme, "regenerate the README table from gesturedb.db.schema.describe()"


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
