"""gesturedb.db.framewriter: per-frame arrays appended a recording at a time, the audio
standardised afterwards in two passes over the file, against numpy on the whole arrays."""
from __future__ import annotations

from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from gesturedb.db import schema
from gesturedb.db.framewriter import MIN_AUDIO_STD, FrameWriter
from gesturedb.features.audio import audio_deltas
from gesturedb.features.controls import CONTROL_NAMES

J, DA = 5, 14


def _recording(rng, n, *, constant_column=False):
    # MFCC-like: columns of very different offsets and scales, so a sum in another order
    # would round differently
    audio = (rng.standard_normal((n, DA)) * rng.uniform(0.01, 80, DA) + rng.uniform(-500, 500, DA)).astype(np.float32)
    if constant_column:
        audio[:, 3] = 7.25
    return SimpleNamespace(
        n_frames=n,
        pose=rng.standard_normal((n, 96)).astype(np.float32),
        positions=rng.standard_normal((n, J, 3)).astype(np.float32),
        rotations=rng.standard_normal((n, J, 4)).astype(np.float32),
        root=rng.standard_normal((n, 3)).astype(np.float32),
        audio_raw=audio,
        velocity_lags=rng.uniform(0, 1e3, 16),
        controls={k: rng.standard_normal(n).astype(np.float32) for k in CONTROL_NAMES},
    )


def _pose_of(positions):
    # any function of one recording's positions alone: it sees them as the file stores them
    return (positions.reshape(positions.shape[0], -1) ** 2 - positions[:, :1, :1].reshape(-1, 1)).astype(np.float32)


@pytest.mark.parametrize("lengths", [[1], [7, 1, 300, 2], [64] * 9, [2500, 13]])
@pytest.mark.parametrize("constant_column", [False, True])
@pytest.mark.parametrize("pose_later", [False, True])
def test_streamed_build_arrays_equal_whole_array_numpy(tmp_path, lengths, constant_column, pose_later):
    """Every per-frame array against numpy on the concatenated recordings; ``pose_later``: the pose
    features come from add_pose, a recording at a time from the stored positions, after the last
    recording (a build whose stride depends on every recording's motion)."""
    rng = np.random.default_rng(len(lengths) * 1000 + sum(lengths))
    recs = [_recording(rng, n, constant_column=constant_column) for n in lengths]
    if pose_later:
        for r in recs:
            r.pose = _pose_of(r.positions.astype(np.float64))
    lags = recs[0].velocity_lags.copy()
    for r in recs[1:]:
        lags = lags + r.velocity_lags
    # what the build computed on the concatenated recordings before it streamed them
    raw = np.concatenate([r.audio_raw for r in recs]).astype(np.float64)
    mean = raw.mean(axis=0)
    std = np.maximum(raw.std(axis=0), MIN_AUDIO_STD)
    want = {
        "frames/pose_features": np.concatenate([r.pose for r in recs]),
        "frames/joint_positions": np.concatenate([r.positions for r in recs]),
        "frames/local_rotations": np.concatenate([r.rotations for r in recs]),
        "frames/root_positions": np.concatenate([r.root for r in recs]),
        "frames/recording": np.concatenate([np.full(n, i, np.int32) for i, n in enumerate(lengths)]),
        "frames/audio_features": ((raw - mean) / std).astype(np.float32),
        "frames/audio_deltas": np.concatenate(
            [audio_deltas(((r.audio_raw.astype(np.float64) - mean) / std).astype(np.float32)) for r in recs]),
    }
    want.update({f"controls/{k}": np.concatenate([r.controls[k] for r in recs]) for k in CONTROL_NAMES})

    dims: dict = {}
    with h5py.File(tmp_path / "f.h5", "w") as h5:
        w = FrameWriter(h5)
        for r in recs:
            if pose_later:
                r.pose = None
            w.add(r)
            assert r.pose is None and r.audio_raw is None and r.controls is None  # the client drops them
        assert w.velocity_lags.tobytes() == lags.tobytes()
        if pose_later:
            assert "frames/pose_features" not in h5
            w.add_pose(_pose_of)
            with pytest.raises(ValueError, match="written already"):
                w.add_pose(_pose_of)
        got_mean, got_std = w.close(dims)
        assert got_mean.tobytes() == mean.tobytes() and got_std.tobytes() == std.tobytes()
        for path, arr in want.items():
            ds = h5[path]
            assert ds.dtype == arr.dtype and ds.shape == arr.shape, path
            assert ds[()].tobytes() == arr.tobytes(), path
        assert h5["frames/pose_features"].attrs[schema.MEAN_ATTR].tobytes() == \
            want["frames/pose_features"].mean(axis=0, dtype=np.float64).tobytes()
        assert sorted(h5[schema.CONTROLS_GROUP]) == sorted(CONTROL_NAMES)
        assert all(h5[f"controls/{k}"].attrs["unit"] is not None for k in CONTROL_NAMES)
    assert dims["F"] == sum(lengths)
    if constant_column:
        assert std[3] == MIN_AUDIO_STD and np.all(want["frames/audio_features"][:, 3] == 0)


def test_rows_of_a_different_width_are_refused(tmp_path):
    rng = np.random.default_rng(0)
    a, b = _recording(rng, 10), _recording(rng, 10)
    b.audio_raw = b.audio_raw[:, :5]
    with h5py.File(tmp_path / "f.h5", "w") as h5:
        w = FrameWriter(h5)
        w.add(a)
        with pytest.raises(schema.SchemaError, match=r"frames/audio_features: expected rows of shape \(14,\), got \(10, 5\) at row 10"):
            w.add(b)


def test_chunks_stay_between_32_kb_and_4_mb(tmp_path):
    """A chunk is the first recording's rows, within [32 kB, 4 MB]: a first recording of 2M
    frames would have made 8 MB chunks of each control; one of 10, 40-byte chunks."""
    from gesturedb.db.framewriter import chunk_rows

    assert chunk_rows(2_000_000, 4) == 1 << 20 and chunk_rows(2_000_000, 384) == (1 << 22) // 384
    assert chunk_rows(951, 4) == 1 << 13 and chunk_rows(951, 56) == 951 and chunk_rows(951, 384) == 951
    assert chunk_rows(10, 1 << 23) == 1  # a row wider than 4 MB: one row a chunk
    rec = _recording(np.random.default_rng(0), 10)
    with h5py.File(tmp_path / "f.h5", "w") as h5:
        FrameWriter(h5).add(rec)
        assert h5[f"{schema.CONTROLS_GROUP}/hand_speed"].chunks == (1 << 13,)
        assert h5["frames/recording"].chunks == (1 << 13,)
        assert h5["frames/audio_features"].chunks == (586, DA)
        assert h5["frames/pose_features"].chunks == (86, 96)
