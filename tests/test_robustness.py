"""Hostile and careless use (issue 12): no data loss, no silent poison, one-line errors, clean kills.

Data loss, concurrency and kills are tested with real processes (subprocess, os.kill).
"""
from __future__ import annotations

import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pytest
import soundfile as sf

from gesturedb.cli.main import main
from gesturedb.errors import InputFileError, ParameterError

STEM = "2_scott_0_1_1"
GESTUREDB = [sys.executable, "-m", "gesturedb.cli"]


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(err: str, *needles: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def digest(path) -> bytes:
    import hashlib

    return hashlib.sha256(Path(path).read_bytes()).digest()


@pytest.fixture()
def db_copy(scott_db_path, tmp_path) -> Path:
    p = tmp_path / "db.h5"
    shutil.copy(scott_db_path, p)
    return p


@pytest.fixture()
def rec_dir(scott_dir, tmp_path) -> Path:
    d = tmp_path / "recs"
    d.mkdir()
    for ext in (".npz", ".wav", ".TextGrid"):
        shutil.copy(scott_dir / f"{STEM}{ext}", d / f"{STEM}{ext}")
    return d


def _tmp_files(folder: Path):
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


# ---------------------------------------------------------------- no command writes over its own inputs

def test_synth_refuses_to_write_over_the_database(db_copy, scott_dir, capsys):
    before = digest(db_copy)
    audio = sorted((scott_dir / "inputs").glob("*.wav"))[0]
    for opt in (["-o", db_copy.with_suffix(".bvh"), "--provenance", db_copy], ["-o", db_copy]):
        code, out, err = run(capsys, "synth", db_copy, "--audio", audio, *opt)
        assert code == 2
        one_line_error(err, str(db_copy))
    assert digest(db_copy) == before
    assert not db_copy.with_suffix(".bvh").exists()


def test_build_refuses_to_write_over_an_input_wav(rec_dir, capsys):
    wav = rec_dir / f"{STEM}.wav"
    before = digest(wav)
    code, out, err = run(capsys, "build", rec_dir, "-o", wav, "-q")
    assert code == 2
    one_line_error(err, "is an input", wav.name)
    assert digest(wav) == before and _tmp_files(rec_dir) == []


def test_outputs_are_all_checked_before_anything_is_written(db_copy, scott_dir, tmp_path, capsys):
    audio = sorted((scott_dir / "inputs").glob("*.wav"))[0]
    out = tmp_path / "out.bvh"
    for bad in (["--npz", tmp_path / "missing" / "x.npz"], ["--provenance", tmp_path / "missing" / "p.json"]):
        code, _, err = run(capsys, "synth", db_copy, "--audio", audio, "-o", out, *bad)
        assert code == 2
        one_line_error(err, "does not exist")
        assert not out.exists()
    code, _, err = run(capsys, "synth", db_copy, "--audio", audio, "-o", tmp_path)
    assert code == 2


# ---------------------------------------------------------------- concurrent edits: all survive

def test_eight_concurrent_mask_edits_all_survive(db_copy):
    names = [f"m{i}" for i in range(8)]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    procs = [subprocess.Popen(GESTUREDB + ["masks", str(db_copy), "add", n, f"left_wrist_height > p{10 + 5 * i}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
             for i, n in enumerate(names)]
    for p in procs:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err.decode()
        assert b"saved" in out
    with h5py.File(db_copy, "r") as h5:
        assert set(names) <= set(h5["masks"])
    assert _tmp_files(db_copy.parent) == []


# ---------------------------------------------------------------- names

def test_bad_mask_names_are_refused_and_a_damaged_file_is_repaired(db_copy, capsys):
    for bad in ("a/b", ".", "", "two words", "x" * 65):
        code, _, err = run(capsys, "masks", db_copy, "add", bad, "left_wrist_height > p50")
        assert code == 2
        one_line_error(err, "mask name")
    # a file damaged by an older version: a nested group under masks/
    with h5py.File(db_copy, "r+") as h5:
        h5["masks"].create_dataset("a/b", data=np.zeros(3, np.uint64))
    code, _, err = run(capsys, "masks", db_copy, "list")
    assert code == 2
    one_line_error(err, "masks/a", "masks DB remove")
    code, out, err = run(capsys, "masks", db_copy, "remove", "a/b")
    assert code == 0, err
    code, out, err = run(capsys, "masks", db_copy, "list")
    assert code == 0 and "masks in the database" in out and "a/b" not in out


# ---------------------------------------------------------------- poisoned input

def test_audio_with_an_absurd_peak_is_rejected_naming_file_and_peak(rec_dir, capsys):
    wav = rec_dir / f"{STEM}.wav"
    x, sr = sf.read(wav, dtype="float32")
    x[1000] = 1e30
    sf.write(wav, x, sr, subtype="FLOAT")
    code, _, err = run(capsys, "build", rec_dir, "-o", rec_dir / "db.h5", "-q")
    assert code == 2
    one_line_error(err, wav.name, "peak 1e+30")
    assert not (rec_dir / "db.h5").exists()


def test_non_finite_data_is_never_written(tmp_path):
    from gesturedb.db import schema
    from gesturedb.errors import SchemaError

    with h5py.File(tmp_path / "x.h5", "w") as h5:
        with pytest.raises(SchemaError, match="audio/mean: expected finite values"):
            schema.write(h5, "audio/mean", np.array([0.0, np.nan]), {})


def test_bvh_frame_rate_outside_1_to_1000_fps_is_refused(data_dir, tmp_path):
    from gesturedb.io import read_motion

    src = (data_dir / "bvh-foreign/AV_8Walk_Meredith_HVHA_Rep1.bvh").read_text()
    for ft, fps in (("20", "0.05"), ("0.0001", "10000")):
        p = tmp_path / "x.bvh"
        lines = src.splitlines()
        i = next(k for k, ln in enumerate(lines) if ln.strip().lower().startswith("frame time"))
        lines[i] = f"Frame Time: {ft}"
        p.write_text("\n".join(lines) + "\n")
        with pytest.raises(InputFileError, match=f"1-1000 fps.*{fps} fps"):
            read_motion(p)


def test_a_given_transcript_is_always_read(db_copy, scott_dir, tmp_path, capsys):
    audio = sorted((scott_dir / "inputs").glob("*.wav"))[0]
    garbage = tmp_path / "g.tsv"
    garbage.write_text("not\ta\ttranscript\tat all\n")
    for t in (tmp_path / "missing.tsv", garbage, tmp_path / "w.docx"):
        if t.suffix == ".docx":
            t.write_text("x")
        code, _, err = run(capsys, "synth", db_copy, "--audio", audio, "--transcript", t, "-o", tmp_path / "o.bvh")
        assert code == 2
        one_line_error(err, t.name)
        assert not (tmp_path / "o.bvh").exists()


@pytest.mark.parametrize("opt", [["--k", str(2**63)], ["--k", "0"], ["--seed", "-1"], ["--export-fps", "1e6"],
                                 ["--export-fps", "nan"], ["--step", "0"]])
def test_cli_numbers_are_range_checked(opt, db_copy, scott_dir, tmp_path, capsys):
    audio = sorted((scott_dir / "inputs").glob("*.wav"))[0]
    with pytest.raises(SystemExit) as info:
        main(["synth", str(db_copy), "--audio", str(audio), "-o", str(tmp_path / "o.bvh"), *opt])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and opt[0] in err.strip().splitlines()[-1]


def test_k_larger_than_the_database_is_refused(db_copy, scott_dir, tmp_path, capsys):
    audio = sorted((scott_dir / "inputs").glob("*.wav"))[0]
    code, _, err = run(capsys, "synth", db_copy, "--audio", audio, "-o", tmp_path / "o.bvh", "--k", "1000000")
    assert code == 2
    one_line_error(err, "k: expected an integer from 1")


# ---------------------------------------------------------------- explicit limits instead of tracebacks

def test_deeply_nested_bvh_is_a_one_line_error(tmp_path):
    from gesturedb.io import read_motion

    depth = 1000
    text = ["HIERARCHY", "ROOT j0", "{", "OFFSET 0 0 0", "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    for i in range(1, depth):
        text += [f"JOINT j{i}", "{", "OFFSET 0 1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    text += ["}"] * depth + ["MOTION", "Frames: 1", "Frame Time: 0.033333", " ".join(["0"] * (3 + 3 * depth))]
    p = tmp_path / "deep.bvh"
    p.write_text("\n".join(text))
    with pytest.raises(InputFileError, match="deep.bvh.*nested more than 200 deep") as info:
        read_motion(p)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("content, match", [("[" * 100_000 + "]" * 100_000, "nested too deeply"),
                                            ('{"words": [{"start": ' + "9" * 5000 + ', "end": 1, "word": "a"}]}',
                                             "invalid JSON")])
def test_hostile_json_transcripts_are_one_line_errors(content, match, tmp_path):
    from gesturedb.io import read_transcript

    p = tmp_path / "t.json"
    p.write_text(content)
    with pytest.raises(InputFileError, match=match) as info:
        read_transcript(p)
    assert "\n" not in str(info.value) and "t.json" in str(info.value)


@pytest.mark.parametrize("expr, match", [("(" * 250 + "a" + ")" * 250, "nested more than 64"),
                                         (" and ".join(["a"] * 1000), "more than 256 terms"),
                                         ("not " * 1000 + "a", "nested more than 64")])
def test_hostile_mask_expressions_are_errors_with_a_self_sufficient_first_line(expr, match):
    from gesturedb.control import parse_mask_expression

    with pytest.raises(ParameterError, match=match) as info:
        parse_mask_expression(expr)
    first = str(info.value).splitlines()[0]
    assert first.startswith("mask expression: column ") and match in first


def test_npz_declaring_a_huge_array_is_refused_before_allocating(tmp_path):
    from gesturedb.io import read_motion

    header = {"descr": "<f4", "fortran_order": False, "shape": (10**12, 165)}
    buf = io.BytesIO()
    import numpy.lib.format as fmt

    fmt.write_array_header_1_0(buf, header)
    p = tmp_path / "huge.npz"
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("poses.npy", buf.getvalue() + b"\0" * 64)
        z.writestr("trans.npy", buf.getvalue())
    assert p.stat().st_size < 2048
    with pytest.raises(InputFileError, match="huge.npz: poses: header declares") as info:
        read_motion(p)
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------- damaged databases: one line naming the dataset

def _set_attr(name, value):
    def f(h5):
        h5.attrs[name] = value
    return f


def _del(path):
    def f(h5):
        del h5[path]
    return f


def _replace(path, fn):
    def f(h5):
        data = h5[path][()]
        del h5[path]
        h5.create_dataset(path, data=fn(data))
    return f


def _poke(path, index, value):
    def f(h5):
        h5[path][index] = value
    return f


DAMAGES = {
    "schema_version string": (_set_attr("schema_version", "one"), "schema_version"),
    "fps zero": (_set_attr("fps", 0.0), "fps"),
    "fps nan": (_set_attr("fps", float("nan")), "fps"),
    "fps string": (_set_attr("fps", "fast"), "fps"),
    "config not json": (_set_attr("config", "{not json"), "config"),
    "config a list": (_set_attr("config", "[1, 2]"), "config"),
    "n_frames wrong": (_set_attr("n_frames", 5), "dimension F"),
    "pose features missing": (_del("frames/pose_features"), "frames/pose_features"),
    "audio features nan": (_replace("frames/audio_features", lambda a: np.full_like(a, np.nan)), "frames/audio_features"),
    "audio std zero": (_replace("audio/std", np.zeros_like), "audio/std"),
    "audio mean nan": (_poke("audio/mean", 0, np.nan), "audio/mean"),
    "zero quaternions": (_replace("frames/local_rotations", np.zeros_like), "frames/local_rotations"),
    "chunk start out of range": (_poke("chunks/start", 0, 10**9), "chunks/start"),
    "chunk recording out of range": (_poke("chunks/recording", 0, 7), "chunks/"),
    "clip length negative": (_poke("clips/length", 0, -5), "clips/"),
    "clip words out of range": (_poke("clips/word_end", 0, 10**6), "clips/word_start"),
    "word recording out of range": (_poke("words/recording", 0, -3), "words/recording"),
    "frame recording out of range": (_poke("frames/recording", 0, 99), "frames/recording"),
    "recording start out of range": (_poke("recordings/start_frame", 0, 10**6), "recordings/start_frame"),
    "parents not topological": (_poke("skeleton/parents", 1, 5), "skeleton/parents"),
    "pose features wrong dtype": (_replace("frames/pose_features", lambda a: a.astype(np.int32)), "frames/pose_features"),
    "pose features a group": (lambda h5: (h5.__delitem__("frames/pose_features"),
                                          h5.create_group("frames/pose_features")), "frames/pose_features"),
    "mask wrong shape": (lambda h5: h5["masks"].create_dataset("short", data=np.zeros(1, np.uint64)), "masks/short"),
    "control wrong shape": (lambda h5: h5["controls"].create_dataset("bad", data=np.zeros(3, np.float32)), "controls/bad"),
}


@pytest.mark.parametrize("damage", list(DAMAGES), ids=lambda s: s.replace(" ", "-"))
def test_each_kind_of_damaged_database_is_a_one_line_error_naming_the_dataset(damage, scott_db_path, scott_dir,
                                                                             tmp_path, capsys):
    fn, needle = DAMAGES[damage]
    db = tmp_path / "db.h5"
    shutil.copy(scott_db_path, db)
    with h5py.File(db, "r+") as h5:
        fn(h5)
    audio = sorted((scott_dir / "inputs").glob("*.wav"))[0]
    for argv in (["info", db], ["synth", db, "--audio", audio, "-o", tmp_path / "o.bvh"], ["masks", db, "list"]):
        code, _, err = run(capsys, *argv)
        assert code == 2, (argv[0], err)
        one_line_error(err, str(db), needle)
    assert not (tmp_path / "o.bvh").exists()


# ---------------------------------------------------------------- disk full, pipes

def test_disk_full_during_an_edit_names_the_file_and_keeps_it(db_copy, monkeypatch):
    import errno

    from gesturedb.db import edit as dbedit
    from gesturedb.db import storage

    before = digest(db_copy)

    def full(src, dst, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(storage, "compact_copy", full)  # the edit's copy of the database
    with pytest.raises(InputFileError, match=f"{db_copy.name}: no space left on device"):
        dbedit.save_mask(db_copy, "calm2", "left_wrist_height < p50")
    assert digest(db_copy) == before and _tmp_files(db_copy.parent) == []


def test_disk_full_during_a_build_names_the_file(tmp_path):
    import errno

    from gesturedb.db import storage

    def fill(h5):
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(InputFileError, match="out.h5: no space left on device"):
        storage.write_atomically(tmp_path / "out.h5", fill)
    assert _tmp_files(tmp_path) == [] and not (tmp_path / "out.h5").exists()


def test_an_input_that_vanishes_during_a_write_is_named_not_the_output(tmp_path):
    """An OSError about another file (an input read while filling, here or on a Dask worker)
    names that file; one about the output or its temporary file stays "cannot write"."""
    import errno

    from gesturedb.db import storage

    out = tmp_path / "out.h5"
    out.write_bytes(b"previous")
    gone = tmp_path / "input.h5"

    def read_input(h5):
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", str(gone))

    with pytest.raises(InputFileError) as info:
        storage.write_atomically(out, read_input)
    assert str(info.value) == f"{gone}: No such file or directory (while writing {out}, which is left as it was)"

    def own_temporary(h5):
        raise PermissionError(errno.EACCES, "Permission denied", h5.filename)

    for fill in (own_temporary, lambda h5: (_ for _ in ()).throw(OSError(errno.EIO, "Input/output error"))):
        with pytest.raises(InputFileError, match=f"^{out}: cannot write: "):
            storage.write_atomically(out, fill)
    assert out.read_bytes() == b"previous" and _tmp_files(tmp_path) == []


def test_listing_into_head_is_quiet(db_copy):
    p = subprocess.run(f"{sys.executable} -m gesturedb.cli masks {db_copy} list | head -1",
                       shell=True, capture_output=True, text=True, timeout=120)
    assert p.stdout.startswith("control features of")
    assert "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr, p.stderr


# ---------------------------------------------------------------- kills

def test_sigterm_during_a_build_leaves_no_temporary_file(rec_dir, tmp_path):
    out = tmp_path / "out.h5"
    out.write_bytes(b"previous")
    p = subprocess.Popen(GESTUREDB + ["build", str(rec_dir), "-o", str(out), "-q", "-j", "1"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=dict(os.environ, OMP_NUM_THREADS="1"))
    # wait until the temporary file exists (the write phase), then terminate
    deadline = time.time() + 120
    while time.time() < deadline and not _tmp_files(tmp_path) and p.poll() is None:
        time.sleep(0.005)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert _tmp_files(tmp_path) == []
    if p.returncode != 0:  # interrupted: the previous file is untouched
        assert p.returncode == 130, err.decode()
        assert out.read_bytes() == b"previous"


@pytest.mark.parametrize("writer", ["write_atomically", "edit"])
def test_sigterm_that_surfaces_as_another_error_is_still_the_interrupt(writer, db_copy, tmp_path):
    """h5py turns an exception raised in its type-conversion callbacks into
    ``TypeError: Operation not defined for data type class``; a SIGTERM arriving
    there (seen in CI) must still end as the interrupt (exit 130), with nothing lost."""
    from gesturedb.db import storage

    def fill(h5):
        h5["x"] = np.arange(3)
        try:
            os.kill(os.getpid(), signal.SIGTERM)  # the handler raises KeyboardInterrupt here
            time.sleep(1)
        except KeyboardInterrupt as exc:
            raise TypeError("Operation not defined for data type class") from exc

    out = tmp_path / "out.h5"
    out.write_bytes(b"previous")
    before = digest(db_copy)
    with pytest.raises(KeyboardInterrupt, match="signal 15"):
        if writer == "write_atomically":
            storage.write_atomically(out, fill)
        else:
            with storage.edit(db_copy) as h5:
                fill(h5)
    assert out.read_bytes() == b"previous" and digest(db_copy) == before
    assert _tmp_files(tmp_path) == [] and _tmp_files(db_copy.parent) == []


def test_a_stale_temporary_file_of_a_dead_process_is_removed_by_the_next_write(db_copy):
    from gesturedb.db import edit as dbedit

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = db_copy.parent / f".{db_copy.name}.{dead.pid}.abc123.tmp"
    stale.write_bytes(b"half a database")
    alive = db_copy.parent / f".{db_copy.name}.{os.getppid()}.def456.tmp"  # a live process's file stays
    alive.write_bytes(b"in progress")
    dbedit.save_mask(db_copy, "calm3", "left_wrist_height < p50")
    assert not stale.exists() and alive.exists()


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _alive(pid: int) -> bool:
    try:
        st = Path(f"/proc/{pid}/stat").read_text().split()[2]
    except OSError:
        return False
    return st != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_build_workers_exit_when_the_build_is_killed(scott_dir, tmp_path):
    d = tmp_path / "two"
    d.mkdir()
    for stem in ("a", "b"):
        for ext in (".npz", ".wav", ".TextGrid"):
            shutil.copy(scott_dir / f"{STEM}{ext}", d / f"{stem}{ext}")
    p = subprocess.Popen(GESTUREDB + ["build", str(d), "-o", str(tmp_path / "x.h5"), "-q", "-j", "2"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    kids: list[int] = []
    while time.time() < deadline and p.poll() is None:
        kids = [k for k in _children(p.pid) if _alive(k)]
        if len(kids) >= 2:
            break
        time.sleep(0.05)
    assert len(kids) >= 2, "the build did not start its 2 workers"
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    deadline = time.time() + 10
    while time.time() < deadline and any(_alive(k) for k in kids):
        time.sleep(0.1)
    assert not any(_alive(k) for k in kids), "workers outlived the killed build"


def test_textgrid_overlap_is_a_one_line_error(scott_dir, tmp_path):
    from gesturedb.io import read_transcript

    text = (scott_dir / f"{STEM}.TextGrid").read_text()
    # make the second interval start before the first one ends
    lines = text.splitlines()
    xmins = [i for i, ln in enumerate(lines) if ln.strip().startswith("xmin =")]
    lines[xmins[4]] = lines[xmins[4]].split("=")[0] + "= 1.45"  # "first" starts inside "the" (1.42-1.52)
    p = tmp_path / "overlap.TextGrid"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match="overlap.TextGrid") as info:
        read_transcript(p)
    assert "\n" not in str(info.value)


def test_absurd_bvh_offsets_name_the_file_and_line(data_dir, tmp_path):
    from gesturedb.io import read_motion

    lines = (data_dir / "bvh-foreign/AV_8Walk_Meredith_HVHA_Rep1.bvh").read_text().splitlines()
    j = [k for k, ln in enumerate(lines) if ln.strip().startswith("OFFSET")][1]
    lines[j] = "OFFSET 1e308 1e308 1e308"
    p = tmp_path / "big.bvh"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match=rf"big.bvh: line {j + 1}: .*OFFSET: expected a length within"):
        read_motion(p)


def test_provenance_is_never_written_with_nan(tmp_path):
    from gesturedb.synth.result import SynthResult

    class Fake:
        def provenance(self):
            return {"steps": [{"audio_dist": float("nan")}]}

    with pytest.raises(InputFileError, match="p.json: provenance: expected finite numbers"):
        SynthResult.write_provenance(Fake(), tmp_path / "p.json")
    assert not (tmp_path / "p.json").exists()


def test_an_output_reaching_an_input_through_a_symlink_or_hard_link_is_refused(tmp_path):
    from gesturedb.io.outputs import check_outputs

    src = tmp_path / "a.wav"
    src.write_bytes(b"RIFF")
    (tmp_path / "link.wav").symlink_to(src)
    os.link(src, tmp_path / "hard.wav")
    for out in ("link.wav", "hard.wav", "sub/../a.wav"):
        (tmp_path / "sub").mkdir(exist_ok=True)
        with pytest.raises(ParameterError, match="is an input of this command"):
            check_outputs({"-o": tmp_path / out}, [src])
    with pytest.raises(ParameterError, match="the same file as -o"):
        check_outputs({"-o": tmp_path / "x.bvh", "--npz": tmp_path / "x.bvh"})
    check_outputs({"-o": tmp_path / "new.bvh", "--npz": None}, [src])  # a fine output passes


# ---------------------------------------------------------------- issue 41, cases 14 and 15: short messages,
# byte-order marks, files called what they are, frame rates a BVH can carry (through the CLI: exit 2, one line)

def test_a_control_item_is_never_echoed_whole():
    """A 125k-character named mask was echoed whole; a long expression is shown around its error."""
    from gesturedb.control.compile import compile_mask
    from gesturedb.control.expression import parse_mask_expression

    c = {"left_wrist_height": np.linspace(0.0, 1.0, 100)}
    with pytest.raises(ParameterError, match=r"^named mask 'big' = 'x{80}'\.\.\. \(125000 characters\): mask "
                                             r"expression: expected at most 10000 characters") as err:
        compile_mask("big", controls=c, named={"big": "x" * 125_000})
    assert len(str(err.value)) < 400 and "\n" not in str(err.value)
    with pytest.raises(ParameterError, match=r"^named: mask names must be identifiers .* got 'y{80}'\.\.\. "
                                             r"\(125001 characters\)$"):
        compile_mask("left_wrist_height > p50", controls=c, named={"y" * 125_000 + "!": "left_wrist_height > p50"})
    many = {f"feature_{i}": np.zeros(100) for i in range(5_000)}
    with pytest.raises(ParameterError, match=r"unknown control feature 'nope'; known features: feature_0, .*"
                                             r"\.\.\. \(5000 in all\)") as err:
        compile_mask("nope > p50", controls=many)
    assert len(str(err.value).splitlines()[0]) < 1500
    expr = " and ".join(["left_wrist_height > p50"] * 300)[:9_000] + " and &"
    with pytest.raises(ParameterError) as err:
        parse_mask_expression(expr)
    lines = str(err.value).splitlines()
    assert lines[0].startswith(f"mask expression: column {len(expr)}: unexpected character '&'")
    assert len(lines) == 3 and all(len(ln) < 200 for ln in lines), lines
    assert lines[1].rstrip().endswith("and &") and lines[2].index("^") == lines[1].index("&")


def test_a_byte_order_mark_is_accepted_by_every_text_reader(scott_dir, data_dir, tmp_path):
    """Excel's "CSV UTF-8" and some exporters start text with a UTF-8 BOM: BVH, transcripts, joint maps."""
    from gesturedb.io import read_bvh, read_transcript
    from gesturedb.io.joints import read_joint_map

    bom = b"\xef\xbb\xbf"
    sources = [data_dir / "bvh-foreign" / "AV_8Walk_Meredith_HVHA_Rep1.bvh", scott_dir / f"{STEM}.TextGrid",
               next((data_dir / "genea2023-transcripts").glob("*.tsv"))]
    js = tmp_path / "words.json"
    js.write_text(json.dumps({"words": [{"start": 0.1, "end": 0.4, "word": "hello"}]}))
    for src in sources + [js]:
        with_bom = tmp_path / ("bom_" + src.name)
        with_bom.write_bytes(bom + src.read_bytes())
        if src.suffix == ".bvh":
            a, b = read_bvh(src), read_bvh(with_bom)
            assert a.skeleton.names == b.skeleton.names and np.array_equal(a.rotations, b.rotations)
        else:
            a, b = read_transcript(src), read_transcript(with_bom)
            assert a.text == b.text and np.array_equal(a.start_s, b.start_s) and len(a.text) > 0, src.name
    jm = tmp_path / "map.json"
    jm.write_bytes(bom + b'{"left_index1": "LeftHandThumb1"}')
    assert read_joint_map(str(jm)) == {"left_index1": "LeftHandThumb1"}


def test_retarget_cli_exits_2_with_one_line_for_hostile_inputs(scott_dir, tmp_path, capsys):
    import rigs

    rig = tmp_path / "rig.bvh"
    rig.write_text(rigs.mixamo_rig())
    out = tmp_path / "out.bvh"
    # random bytes named .npz: called what they are (was "Cannot load file containing pickled data")
    noise = tmp_path / "noise.npz"
    noise.write_bytes(np.random.default_rng(0).bytes(4096))
    code, _, err = run(capsys, "retarget", noise, "--to", rig, "-o", out)
    assert code == 2 and "noise.npz: expected an .npz archive" in one_line_error(err, "not a zip archive")
    # SMPL-X at 1e9 fps: refused where it is read, naming the file (was written to a BVH read_bvh refuses)
    d = dict(np.load(scott_dir / f"{STEM}.npz"))
    d["mocap_frame_rate"] = np.array(1e9)
    fast = tmp_path / "fast.npz"
    np.savez(fast, **{k: v[:30] if k in ("poses", "trans") else v for k, v in d.items()})
    code, _, err = run(capsys, "retarget", fast, "--to", rig, "-o", out)
    assert code == 2
    one_line_error(err, "fast.npz: mocap_frame_rate: expected one frame rate of 1 to 1000 Hz")
    # a rig declaring 10^7 channels: refused at the count, one short line (was a 100 MB line)
    huge = tmp_path / "huge.bvh"
    huge.write_text("HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 0\nCHANNELS 10000000 " + "Xrotation " * 100_000
                    + "\n}\nMOTION\nFrames: 1\nFrame Time: 0.03\n0\n")
    code, _, err = run(capsys, "retarget", scott_dir / f"{STEM}.npz", "--to", huge, "-o", out)
    assert code == 2 and len(one_line_error(err, "huge.bvh: line 5: Hips CHANNELS: expected 0 to 6 channels")) < 300
    assert not out.exists() and not list(tmp_path.glob("*.tmp"))


def test_reading_speech_costs_about_its_samples(tmp_path):
    """issue 41, case 16: read_audio's whole-file temporaries (NaN mask, |x|, the channel mean) were 2-3x
    the samples; checks and mix-down now go in slices, with the same samples and messages."""
    import tracemalloc

    from gesturedb.io.audio import read_audio

    rng = np.random.default_rng(3)
    n = 16000 * 120
    stereo = (0.1 * rng.standard_normal((n, 2))).astype(np.float32)
    p = tmp_path / "stereo.wav"
    sf.write(p, stereo, 16000, subtype="FLOAT")
    tracemalloc.start()
    try:
        y, sr = read_audio(p, sr=None)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert sr == 16000 and y.tobytes() == stereo.mean(axis=1, dtype=np.float32).tobytes()
    # the file's frames (2 channels) and the mono result: 3 x 7.7 MB, plus slices
    assert peak < 3 * n * 4 + 6e6, peak / 1e6  # the old whole-file checks: 34.6 MB here
    stereo[n - 7, 1] = np.nan
    sf.write(p, stereo, 16000, subtype="FLOAT")
    with pytest.raises(InputFileError, match=rf"stereo.wav: sample {n - 7} \(t = 120.000 s, channel 1\) is not "
                                             r"finite: nan$"):
        read_audio(p)
