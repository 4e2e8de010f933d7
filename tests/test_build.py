"""Building a database from the real BEAT2 recording, and what a bad input does."""
from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import wave
from pathlib import Path

import h5py
import numpy as np
import pytest
import soundfile as sf

import gesturedb
from gesturedb.db import schema
from gesturedb.db.build import BuildConfig, pair_inputs
from gesturedb.errors import InputFileError, ParameterError, SchemaError

try:  # tests/ is on sys.path when it is not a package, the repo root when it is
    from dbcontent import differing
except ModuleNotFoundError:  # pragma: no cover
    from tests.dbcontent import differing

STEM = "2_scott_0_1_1"


def test_frame_count_matches_duration(scott_db):
    # 1906 frames at 30 fps = 63.53 s; at 15 fps every other frame
    assert scott_db.fps == 15.0
    assert scott_db.n_frames == math.ceil(1906 * 15 / 30)
    rec = scott_db.recordings[0]
    assert rec.name == STEM and rec.speaker == "scott" and rec.source_fps == 30.0
    assert abs(rec.duration_s - 63.5) < 0.1


def test_arrays_have_declared_shapes_and_are_search_ready(scott_db):
    F = scott_db.n_frames
    for arr, shape in [
        (scott_db.pose_features, (F, 150)),  # 8 feature joints and the 2 ankles, 5 frames
        (scott_db.audio_features, (F, 14)),
        (scott_db.audio_deltas, (F, 14)),
        (scott_db.joint_positions, (F, 55, 3)),
        (scott_db.local_rotations, (F, 55, 4)),
    ]:
        assert arr.shape == shape and arr.dtype == np.float32 and arr.flags.c_contiguous
        assert np.isfinite(arr).all()
    # standardised audio: zero mean, unit variance over the database
    np.testing.assert_allclose(scott_db.audio_features.mean(0), 0, atol=1e-4)
    np.testing.assert_allclose(scott_db.audio_features.std(0), 1, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(scott_db.local_rotations, axis=-1), 1, atol=1e-5)
    assert scott_db.joint_names[20] == "left_wrist"


def test_chunks_tile_the_recording(scott_db):
    c = scott_db.chunks
    assert c.start.dtype == np.int64 and c.length.dtype == np.int64
    assert c.start[0] == 0 and np.all(c.start[1:] == c.start[:-1] + c.length[:-1])
    assert c.start[-1] + c.length[-1] == scott_db.n_frames
    assert np.all(c.length[:-1] == 64) and 0 < c.length[-1] <= 64


def test_clips_follow_the_word_gaps(scott_db, scott_dir):
    from gesturedb.io import read_transcript

    words = read_transcript(scott_dir / f"{STEM}.TextGrid")
    assert len(scott_db.words) == len(words) == 199
    np.testing.assert_allclose(scott_db.words.start_s, words.start_s)
    gaps = words.start_s[1:] - words.end_s[:-1]
    cl = scott_db.clips
    gap_s = float(scott_db.config["gap_s"])  # the build's default "auto" stores the gap it chose
    assert 0.1 <= gap_s <= 0.4
    assert len(cl) == int((gaps > gap_s).sum()) + 1
    # clips tile the recording and every word is in exactly one clip
    assert cl.start[0] == 0 and cl.start[-1] + cl.length[-1] == scott_db.n_frames
    assert np.all(cl.start[1:] == cl.start[:-1] + cl.length[:-1])
    assert cl.word_start[0] == 0 and cl.word_end[-1] == len(words)
    assert np.all(cl.word_start[1:] == cl.word_end[:-1])
    fps = scott_db.fps
    for k in range(len(cl)):
        ws, we = cl.word_start[k], cl.word_end[k]
        # no long gap inside a clip, and its words lie inside it
        assert np.all(gaps[ws:we - 1] <= gap_s)
        assert words.start_s[ws] >= cl.start[k] / fps - 1e-9
        assert words.start_s[we - 1] < (cl.start[k] + cl.length[k]) / fps
    # audio rhythm: a clip with words has onset bits; signatures differ between clips
    assert np.all(cl.rhythm_audio != 0) and np.all(cl.rhythm_motion != 0)
    assert cl.style.shape == (len(cl), 3) and np.all(cl.style[:, 0] > 0.05)


def test_build_twice_gives_identical_content(scott_dir, scott_db_path, tmp_path):
    again = tmp_path / "again.h5"
    gesturedb.build([scott_dir], again, workers=2).close()

    assert differing(scott_db_path, again) == []


def test_mirror_doubles_the_database(scott_dir, tmp_path):
    with gesturedb.build([scott_dir], tmp_path / "m.h5", mirror=True) as db:
        assert [r.name for r in db.recordings] == [STEM, STEM + "~mirror"]
        assert db.n_frames == 2 * 953
        a, b = db.recordings
        left, right = db.joint_names.index("left_wrist"), db.joint_names.index("right_wrist")
        P = db.joint_positions
        # the mirrored copy's left wrist is the original right wrist reflected in x
        np.testing.assert_allclose(P[b.start_frame:b.stop_frame, left, 0], -P[:a.n_frames, right, 0], atol=1e-4)
        np.testing.assert_allclose(P[b.start_frame:b.stop_frame, left, 1], P[:a.n_frames, right, 1], atol=1e-4)
        assert len(db.words) == 2 * 199


def test_schema_version_mismatch_is_a_clear_error(scott_db_path, tmp_path):
    bad = tmp_path / "old.h5"
    shutil.copy(scott_db_path, bad)
    with h5py.File(bad, "r+") as h5:
        h5.attrs["schema_version"] = schema.SCHEMA_VERSION + 1
    with pytest.raises(SchemaError, match=rf"old.h5: schema_version: expected {schema.SCHEMA_VERSION}, got {schema.SCHEMA_VERSION + 1}"):
        gesturedb.open(bad)
    with pytest.raises(InputFileError, match="not an HDF5 file"):
        (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all")
        gesturedb.open(tmp_path / "junk.h5")


def test_pairing_reports_what_it_skipped(scott_dir):
    p = pair_inputs([scott_dir / "inputs"])
    assert p.recordings == []
    reasons = {os.path.basename(s.path): s.reason for s in p.skipped}
    assert "no motion file" in reasons["2_scott_0_2_2.wav"]
    p = pair_inputs([scott_dir])
    assert [r.name for r in p.recordings] == [STEM]
    assert p.recordings[0].transcript.endswith(".TextGrid")


def test_unknown_build_option_lists_the_valid_ones():
    with pytest.raises(ParameterError, match=r"\['bogus'\]: not known; options are .*'fps'"):
        BuildConfig.from_kwargs(bogus=1)
    with pytest.raises(ParameterError, match="fps: expected a positive number"):
        BuildConfig(fps=0)


# --------------------------------------------------------------------------
# bad input: one clear error naming the file and the field, nothing left behind
# --------------------------------------------------------------------------

@pytest.fixture()
def recording(scott_dir, tmp_path):
    """A writable copy of the real recording in its own folder."""
    d = tmp_path / "in"
    d.mkdir()
    for ext in (".npz", ".wav", ".TextGrid"):
        shutil.copy(scott_dir / f"{STEM}{ext}", d / f"{STEM}{ext}")
    return d


def _assert_nothing_left(folder: Path, keep=()):
    left = sorted(p.name for p in folder.iterdir() if p.name not in keep)  # no temporary, no lock file
    assert left == [], left


def _build_fails(recording, tmp_path, exc, match):
    out_dir = tmp_path / "out"
    out_dir.mkdir(exist_ok=True)
    with pytest.raises(exc, match=match):
        gesturedb.build([recording], out_dir / "db.h5")
    _assert_nothing_left(out_dir)


def test_nan_in_motion(recording, tmp_path):
    d = dict(np.load(recording / f"{STEM}.npz", allow_pickle=True))
    d["poses"] = d["poses"].copy()
    d["poses"][100, 60] = np.nan
    np.savez(recording / f"{STEM}.npz", **d)
    _build_fails(recording, tmp_path, InputFileError, rf"{STEM}.npz: .*poses.*(NaN|nan|finite)")


def test_audio_and_motion_lengths_differ(recording, tmp_path):
    x, sr = sf.read(recording / f"{STEM}.wav", dtype="float32")
    sf.write(recording / f"{STEM}.wav", x[: sr * 50], sr, subtype="FLOAT")
    _build_fails(recording, tmp_path, InputFileError, rf"{STEM}.wav: duration: expected within 1 s of the motion \(63.53 s .*\), got 50.00 s")


def test_empty_wav(recording, tmp_path):
    with wave.open(str(recording / f"{STEM}.wav"), "wb") as w:
        w.setnchannels(1), w.setsampwidth(2), w.setframerate(16000)
    _build_fails(recording, tmp_path, InputFileError, rf"{STEM}.wav: .*(empty|no audio samples|0 samples)")


def test_textgrid_without_words_tier(recording, tmp_path):
    tg = recording / f"{STEM}.TextGrid"
    tg.write_text(tg.read_text().replace('name = "words"', 'name = "sentences"'))
    _build_fails(recording, tmp_path, InputFileError, rf"{STEM}.TextGrid: .*words.*sentences")


@pytest.mark.parametrize("cut", ["mid-line", "line-boundary"])
def test_truncated_bvh(data_dir, tmp_path, cut):
    src = data_dir / "bvh-foreign" / "AV_8Walk_Meredith_HVHA_Rep1.bvh"
    d = tmp_path / "in"
    d.mkdir()
    text = src.read_text()
    n = int(len(text) * 0.6)
    if cut == "line-boundary":
        n = text.rindex("\n", 0, n) + 1
        match = r"walk.bvh: .*1064.*(637|636)"  # Frames: 1064 promised, 636 or so present
    else:
        match = r"walk.bvh: line \d+ \(frame \d+\): expected 72 values \(from CHANNELS\), got \d+"
    (d / "walk.bvh").write_text(text[:n])
    sf.write(d / "walk.wav", np.zeros(16000 * 9, np.float32), 16000)
    _build_fails(d, tmp_path, InputFileError, match)


def test_failed_build_keeps_the_existing_database(recording, scott_db_path, tmp_path):
    out = tmp_path / "keep"
    out.mkdir()
    target = out / "db.h5"
    shutil.copy(scott_db_path, target)
    before = target.read_bytes()
    x, sr = sf.read(recording / f"{STEM}.wav", dtype="float32")
    sf.write(recording / f"{STEM}.wav", x[: sr * 10], sr, subtype="FLOAT")
    with pytest.raises(InputFileError):
        gesturedb.build([recording], target)
    assert target.read_bytes() == before
    _assert_nothing_left(out, keep=("db.h5",))


def test_each_transcript_is_read_once(scott_dir, tmp_path, monkeypatch):
    """The automatic gap reads every transcript before any recording is processed; the
    recordings take those words instead of parsing their files again. The database is the one a
    build with that gap given explicitly writes (where each recording reads its own file)."""
    import gesturedb.db.build
    import gesturedb.io
    import gesturedb.io.transcripts as T

    reads = []
    real = T.read_transcript

    def counting(path, *a, **kw):
        reads.append(Path(path).name)
        return real(path, *a, **kw)

    monkeypatch.setattr(T, "read_transcript", counting)
    monkeypatch.setattr(gesturedb.io, "read_transcript", counting)
    monkeypatch.setattr(gesturedb.db.build, "read_transcript", counting)  # imported at its top
    with gesturedb.build([scott_dir], tmp_path / "auto.h5", mirror=True) as db:
        gap = float(db.config["gap_s"])
    assert reads == [f"{STEM}.TextGrid"]
    reads.clear()
    gesturedb.build([scott_dir], tmp_path / "given.h5", mirror=True, gap_s=gap).close()
    assert reads == [f"{STEM}.TextGrid"]
    assert differing(tmp_path / "auto.h5", tmp_path / "given.h5") == []


def test_the_file_is_not_padded_by_its_growable_datasets(scott_db_path):
    """The frame arrays grow as recordings arrive, in chunks of at most one recording, and the
    database stores them contiguous (so that open maps them): the file stays about 2.1 kB per
    frame (whole 4 MB chunks made the real database four times larger)."""
    with h5py.File(scott_db_path, "r") as h5:
        n = int(h5.attrs["n_frames"])
        assert all(h5[p].chunks is None for p in schema.CONTIGUOUS_FIELDS)
    assert os.path.getsize(scott_db_path) / n < 3000


def test_narrow_frame_arrays_are_not_cut_into_tiny_chunks(scott_db_path):
    """Chunks of one recording's rows, but at least 32 kB: the controls, the recording index and
    the audio (4 to 56 bytes a frame) were 3.8 kB chunks, three times slower to read back."""
    from gesturedb.db.framewriter import MIN_CHUNK_BYTES

    with h5py.File(scott_db_path, "r") as h5:
        # the per-frame arrays were chunked so too; the database now stores them contiguous
        narrow = [f"{schema.CONTROLS_GROUP}/{k}" for k in h5[schema.CONTROLS_GROUP]]
        for path in narrow:
            ds = h5[path]
            assert ds.chunks is not None and ds.chunks[0] * ds.dtype.itemsize * int(np.prod(ds.shape[1:])) \
                >= MIN_CHUNK_BYTES, path


def test_streamed_build_equals_the_whole_arrays(scott_dir, tmp_path):
    """The real recording cut into three takes, mirrored (six recordings of different lengths):
    the streamed file's audio, deltas, controls, recording index, percentile masks and pose
    features are those computed by numpy on every recording's arrays concatenated, bit for bit
    (the pose features with the stride of the whole database's motion timescale, computed from
    each recording's positions by the recording's own pass given that stride)."""
    from gesturedb import control
    from gesturedb.db.build import process_recording
    from gesturedb.db.takes import RecordingSource
    from gesturedb.features.audio import audio_deltas
    from gesturedb.features.pose import motion_timescale, timescale_pose_stride

    files = [str(scott_dir / f"{STEM}{ext}") for ext in (".npz", ".wav", ".TextGrid")]
    sources = [RecordingSource(name, *files, span_s=span)
               for name, span in (("a", (0.0, 20.0)), ("b", (20.0, 41.3)), ("c", (41.3, 63.5)))]
    config = dict(mirror=True, gap_s=0.3, graph=False)
    with gesturedb.build(sources, tmp_path / "db.h5", **config):
        pass
    recs = [r for s in sources for r in process_recording(s, BuildConfig.from_kwargs(**config))]
    assert len({r.n_frames for r in recs}) == 3 and len(recs) == 6
    raw = np.concatenate([r.audio_raw for r in recs]).astype(np.float64)
    mean, std = raw.mean(axis=0), np.maximum(raw.std(axis=0), 1e-6)
    controls = {k: np.concatenate([r.controls[k] for r in recs]).astype(np.float32) for k in sorted(recs[0].controls)}
    want = {
        "audio/mean": mean, "audio/std": std,
        "frames/audio_features": ((raw - mean) / std).astype(np.float32),
        "frames/audio_deltas": np.concatenate(
            [audio_deltas(((r.audio_raw.astype(np.float64) - mean) / std).astype(np.float32)) for r in recs]),
        "frames/recording": np.concatenate([np.full(r.n_frames, i, np.int32) for i, r in enumerate(recs)]),
    }
    timescale = motion_timescale(sum(r.velocity_lags for r in recs), 15.0)
    stride = timescale_pose_stride(timescale, 15.0)
    assert stride == 2 and all(r.pose is None for r in recs)
    given = [r for s in sources for r in process_recording(s, BuildConfig.from_kwargs(**config, pose_stride=stride))]
    want["frames/pose_features"] = np.concatenate([r.pose for r in given])
    want.update({f"controls/{k}": v for k, v in controls.items()})
    want.update({f"masks/{k}": m.words for k, m in control.percentile_masks(controls).items()})
    with h5py.File(tmp_path / "db.h5", "r") as h5:
        assert [s.decode() for s in h5["recordings/name"][()]] == [r.name for r in recs]
        assert json.loads(h5.attrs["config"])["pose_stride"] == stride
        assert h5.attrs["motion_timescale_s"] == timescale
        assert sorted(k for k in h5["masks"] if k.endswith(("_high", "_low"))) == sorted(k[6:] for k in want if k.startswith("masks/"))
        for path, arr in want.items():
            got = h5[path][()]
            assert got.dtype == arr.dtype and got.tobytes() == arr.tobytes(), path


# ---------------------------------------------------------------- disk full (issue 41, case 8)

from diskfull import FAIL_AFTER as _FAIL_AFTER  # noqa: E402  (tests/diskfull.py)


@contextlib.contextmanager
def _small_filesystem(folder: Path, size_kb: int):
    """A tmpfs of ``size_kb`` mounted on ``folder`` (needs root; skips with the reason otherwise)."""
    import subprocess

    folder.mkdir()
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(folder)],
                       capture_output=True, text=True)
    if p.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({(p.stderr or p.stdout).strip()}): the disk-full "
                    "build with injected write failures still runs")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


@pytest.mark.parametrize("free", [0.08, 0.8], ids=["full-in-the-frames", "full-near-the-end"])
@pytest.mark.parametrize("disk", ["tmpfs", "injected"])
def test_disk_full_during_a_build_is_one_line_and_keeps_the_database(disk, free, scott_dir, scott_db_path,
                                                                     tmp_path):
    """The disk fills up while `gesturedb build` writes over an existing database: one line
    naming the database and the full disk, exit 2 (no h5py tracebacks, no segfault: HDF5's
    failed close had freed memory twice, exit 139 after the error), the old database byte for
    byte, no temporary file. On a real small file system (tmpfs, root only) and with the
    writes failing from a given byte on (anywhere)."""
    import subprocess
    import sys

    old = scott_db_path.read_bytes()
    free_kb = int(len(old) * free) // 1024  # room for this fraction of the new database (as large as the old)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if disk == "tmpfs":
        folder = tmp_path / "small"
        ctx = _small_filesystem(folder, len(old) // 1024 + free_kb)
        cmd = [sys.executable, "-m", "gesturedb.cli"]
    else:
        folder = tmp_path / "out"
        folder.mkdir()
        ctx = contextlib.nullcontext()
        cmd = [sys.executable, "-c", _FAIL_AFTER, str(free_kb * 1024)]
    with ctx:
        target = folder / "db.h5"
        target.write_bytes(old)
        p = subprocess.run(cmd + ["build", str(scott_dir), "-o", str(target), "-q", "-j", "1"], env=env,
                           capture_output=True, text=True, timeout=600)
        assert p.returncode == 2, (p.returncode, p.stderr[-3000:])
        assert p.stderr.splitlines() == [f"gesturedb build: error: {target}: no space left on device while writing "
                                         "it; the previous file (if any) is unchanged"], p.stderr[-3000:]
        assert target.read_bytes() == old
        _assert_nothing_left(folder, keep=("db.h5",))


def test_a_refused_write_is_read_back_from_memory_and_stops_the_writer(tmp_path, monkeypatch):
    """After the disk refused a write, HDF5 still reads back everything it wrote (held in
    memory), so it can close every handle; the writer's next checkpoint raises the disk's
    error, and the old file stays."""
    import errno

    from gesturedb.db import storage

    out = tmp_path / "out.h5"
    out.write_bytes(b"previous")
    real, budget = os.pwrite, [200_000]

    def pwrite(fd, data, offset):
        n = min(len(data), budget[0])
        if n == 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        budget[0] -= n
        return real(fd, memoryview(data)[:n], offset)

    seen = {}

    def fill(h5):
        rng = np.random.default_rng(0)
        for i in range(12):  # 12 x 80 kB, chunked and compressed, each closed as it is written
            x = rng.standard_normal((100, 100))
            h5.create_dataset(f"d{i}", data=x, chunks=(10, 100), compression="gzip")
            seen[i] = x
        h5.flush()
        for i, x in seen.items():  # read back, from disk and from memory
            assert np.array_equal(h5[f"d{i}"][()], x), i
        assert seen and h5.attrs.get("x") is None
        storage.check_writes(h5)
        raise AssertionError("the checkpoint did not stop the writer")

    monkeypatch.setattr(os, "pwrite", pwrite)
    with pytest.raises(InputFileError, match=r"out\.h5: no space left on device while writing it"):
        storage.write_atomically(out, fill)
    monkeypatch.undo()
    assert budget == [0] and len(seen) == 12
    assert out.read_bytes() == b"previous"
    _assert_nothing_left(tmp_path, keep=("out.h5",))
    # the HDF5 library is still sound: the next file is written and read as usual
    storage.write_atomically(out, lambda h5: h5.create_dataset("x", data=np.arange(5)))
    with h5py.File(out, "r") as h5:
        assert h5["x"][()].tolist() == [0, 1, 2, 3, 4]
