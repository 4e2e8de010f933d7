"""The build's per-frame arrays, written a recording at a time as the recordings arrive.

A build that held every recording until the end, and then concatenated them, needed
about 3.5 kB per frame on the client: 19 GB at 100 hours, 38 GB mirrored. Here each
recording's per-frame arrays (pose features, joint positions and rotations, root,
audio features, control features, recording index) are appended to growable chunked
datasets as soon as it arrives, and the recording drops them. What the client keeps
per recording is its clips, chunks and words.

The audio features are standardised with the mean and standard deviation of the whole
database, which are known only after the last recording. They are therefore written
raw first (they are float32 until standardised, so the dataset holds them exactly), and
:meth:`FrameWriter.close` makes two passes over the file, a recording at a time: the
squared deviations, then the standardised features (in place) and their deltas. Both statistics are accumulated row after row in float64, which is what
numpy's ``mean``/``std`` along axis 0 of the whole array do, so the file has the
bits of a build that concatenated everything (tested).
"""
from __future__ import annotations

import numpy as np

from gesturedb.db import schema, store
from gesturedb.features.audio import audio_deltas
from gesturedb.features.controls import CONTROL_DOCS, CONTROL_UNITS

#: standard deviations under this are taken as this, so a constant feature is not divided by zero
MIN_AUDIO_STD = 1e-6
#: smallest chunk of a per-frame dataset (rows of float32 or int32), bytes
MIN_CHUNK_BYTES = 1 << 15


def chunk_rows(first_rows: int, row_bytes: int) -> int:
    """Rows per chunk of a growable per-frame dataset whose first recording has ``first_rows``.

    The first recording's rows, so that a small database is not padded to 4 MB chunks; at most
    :attr:`schema.RowWriter.CHUNK_BYTES` (4 MB); at least :data:`MIN_CHUNK_BYTES`: the narrow
    arrays' chunks of one 951-frame recording were 3.8 kB, and reading them back took 3x as
    long as 32 kB chunks.
    """
    row_bytes = max(1, int(row_bytes))
    lo = -(-MIN_CHUNK_BYTES // row_bytes)
    return max(1, min(max(int(first_rows), lo), schema.RowWriter.CHUNK_BYTES // row_bytes))


class FrameWriter:
    """Every per-frame dataset of a build, appended a recording at a time.

    ``add(r)`` writes recording ``r``'s rows after those of the recordings before it
    and sets its per-frame attributes to None; ``close(dims)`` standardises the audio
    and returns its ``(mean, std)``, each of shape (Da,) float64. Recordings that come
    without pose features (their stride is chosen from the whole database's motion, whose
    velocity sums :attr:`velocity_lags` adds up) get them from :meth:`add_pose` before
    ``close``.
    """

    FIELDS = ((schema.POSE_FEATURES, "pose"), (schema.JOINT_POSITIONS, "positions"),
              (schema.LOCAL_ROTATIONS, "rotations"), (schema.ROOT_POSITIONS, "root"))

    def __init__(self, h5):
        self.h5 = h5
        self.rows: list[schema.RowWriter] = []
        self.fields: list[str] = []  # the RecordingData attribute each of ``rows`` writes
        self.controls: dict[str, object] = {}
        self.lengths: list[int] = []
        self.audio_sum: np.ndarray | None = None
        #: (L + 1,) float64: the recordings' features.pose.velocity_lag_products, added in input order
        self.velocity_lags: np.ndarray | None = None

    def _open(self, r) -> None:
        def rows(row_shape) -> int:
            return chunk_rows(r.n_frames, 4 * int(np.prod(row_shape, dtype=np.int64)))

        self.rows, self.fields = [], []
        for path, attr in self.FIELDS:
            if getattr(r, attr) is None:  # the pose features, written by add_pose
                continue
            shape = getattr(r, attr).shape[1:]
            self.rows.append(schema.RowWriter(self.h5, path, shape, chunk_rows=rows(shape)))
            self.fields.append(attr)
        self.recording = schema.RowWriter(self.h5, schema.FRAME_RECORDING, (), chunk_rows=rows(()))
        da = r.audio_raw.shape[1:]
        self.audio = schema.RowWriter(self.h5, schema.AUDIO_FEATURES, da, chunk_rows=rows(da))
        self.deltas = schema.RowWriter(self.h5, schema.AUDIO_DELTAS, da, chunk_rows=rows(da))
        store.ensure_group(self.h5, schema.CONTROLS_GROUP)
        for k in sorted(r.controls):
            self.controls[k] = store.create(self.h5, f"{schema.CONTROLS_GROUP}/{k}", shape=(0,), dtype=np.float32,
                                            chunk_rows=rows(()),
                                            attrs={"unit": CONTROL_UNITS.get(k, ""), "doc": CONTROL_DOCS.get(k, "")})

    def add(self, r) -> None:
        """Append recording ``r`` (a :class:`gesturedb.db.build.RecordingData`)."""
        if not self.rows:
            self._open(r)
        for rows, attr in zip(self.rows, self.fields):
            rows.write(getattr(r, attr))
            setattr(r, attr, None)
        lags = np.asarray(r.velocity_lags, dtype=np.float64)
        self.velocity_lags = lags.copy() if self.velocity_lags is None else self.velocity_lags + lags
        self.recording.write(np.full(r.n_frames, len(self.lengths), np.int32))
        self.audio.write(r.audio_raw)
        self.audio_sum = schema.add_rows(self.audio_sum, r.audio_raw)
        r.audio_raw = None
        for k, ds in self.controls.items():
            store.append(ds, np.asarray(r.controls[k], dtype=np.float32))
        r.controls = None
        self.lengths.append(int(r.n_frames))

    def _recordings(self):
        start = 0
        for n in self.lengths:
            yield start, start + n
            start += n

    def add_pose(self, pose_of, *, progress: bool = False) -> None:
        """The pose features of every recording added, from its joint positions as stored.

        ``pose_of(positions)`` takes one recording's ``(n, J, 3)`` float64 positions (metres; the
        float32 values the file holds, which is what a recording's own features are computed
        from) and returns its ``(n, Dp)`` float32 pose features. One recording at a time, so
        memory stays that of the longest recording. ``progress``: a bar over the frames on stderr
        (about 8 s a million frames: a minute and a half at 100 hours, mirrored).
        """
        if schema.POSE_FEATURES in self.h5:
            raise ValueError("add_pose: the pose features are written already")
        positions = self.rows[self.fields.index("positions")].ds
        rows = bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=sum(self.lengths), unit="frame", desc="pose features", disable=None)
        try:
            for a, b in self._recordings():
                pose = pose_of(positions[a:b].astype(np.float64))
                if rows is None:
                    rows = schema.RowWriter(self.h5, schema.POSE_FEATURES, pose.shape[1:],
                                            chunk_rows=chunk_rows(b - a, 4 * int(np.prod(pose.shape[1:]))))
                rows.write(pose)
                if bar is not None:
                    bar.update(b - a)
        finally:
            if bar is not None:
                bar.close()
        self.rows.append(rows)
        self.fields.append("pose")

    def close(self, dims: dict) -> tuple[np.ndarray, np.ndarray]:
        """After the last recording: rows checked against ``dims``, the audio standardised in
        place and its deltas written; returns the audio ``(mean, std)``, (Da,) float64 each."""

        for rows in self.rows + [self.recording]:
            rows.close(dims)
        F = self.audio.n
        ds = self.audio.ds
        mean = self.audio_sum / F
        sq = None
        for a, b in self._recordings():
            x = ds[a:b].astype(np.float64) - mean
            sq = schema.add_rows(sq, x * x)
        # cosine distance on raw MFCCs would be dominated by c0 and energy
        std = np.maximum(np.sqrt(sq / F), MIN_AUDIO_STD)
        for a, b in self._recordings():
            z = ((ds[a:b].astype(np.float64) - mean) / std).astype(np.float32)
            ds[a:b] = z
            self.deltas.write(audio_deltas(z))
        self.audio.close(dims)
        self.deltas.close(dims)
        return mean, std
