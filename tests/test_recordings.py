"""Recordings from other capture pipelines: their BVH conventions, units, asymmetric skeletons, speakers.

The real SMPL-X take is written as GENEA / Talking With Hands, ZEGGS and Mixamo BVH
files (``tests/pipelines.py``, Euler angles from scipy) at 30, 60 and 120 fps, and
the database built from each must match the one built from the source npz.
"""
from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import soundfile as sf

import gesturedb
from gesturedb.db.build import RecordingSource, infer_speaker, mirrored_copy, read_pairing_file
from gesturedb.errors import InputFileError, ParameterError
from gesturedb.io.bvh import describe_length_unit, guess_length_unit, parse_length_unit, read_bvh, write_bvh
from gesturedb.io.smplx import read_smplx
from gesturedb.motion import Motion, Skeleton
from gesturedb.synth import Searcher

try:
    from pipelines import CONVENTIONS, write_convention
except ImportError:  # collected as a package
    from tests.pipelines import CONVENTIONS, write_convention

STEM = "2_scott_0_1_1"
# a cut inside a pause of the transcript (no word starts between 20.16 and 20.3 s), so every
# frame rate's motion keeps the same words
CUT_S = 20.2


@pytest.fixture(scope="module")
def clip(scott_dir, tmp_path_factory):
    """The first 20.2 s of the real take: motion, a WAV and a TSV transcript cut there, and the reference database."""
    from gesturedb.io import read_transcript

    d = tmp_path_factory.mktemp("clip")
    motion = read_smplx(scott_dir / f"{STEM}.npz")
    n = int(round(CUT_S * motion.fps))
    y, sr = sf.read(scott_dir / f"{STEM}.wav", dtype="float32")
    wav = d / "speech.wav"
    sf.write(wav, y[: int(round(CUT_S * sr))], sr, subtype="FLOAT")
    words = read_transcript(scott_dir / f"{STEM}.TextGrid")
    keep = words.start_s < CUT_S
    tsv = d / "speech.tsv"
    tsv.write_text("".join(f"{s:.3f}\t{min(e, CUT_S):.3f}\t{t}\n" for s, e, t in words[keep]))
    ref = d / "ref.h5"
    src = RecordingSource("scott", str(scott_dir / f"{STEM}.npz"), str(scott_dir / f"{STEM}.wav"),
                          str(scott_dir / f"{STEM}.TextGrid"), span_s=(0.0, CUT_S))
    gesturedb.build([src], ref, graph=False).close()
    return SimpleNamespace(dir=d, motion=motion[:n], wav=wav, tsv=tsv, ref=ref)


def _recording(folder: Path, clip, motion_file: Path) -> Path:
    """A folder holding one recording: the motion file plus the clip's speech and words under its stem."""
    folder.mkdir(parents=True, exist_ok=True)
    stem = motion_file.stem
    os.link(clip.wav, folder / f"{stem}.wav")
    os.link(clip.tsv, folder / f"{stem}.tsv")
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("convention", sorted(CONVENTIONS))
def test_pipeline_conventions_build_the_same_database(clip, tmp_path, convention):
    folder = tmp_path / convention
    folder.mkdir()
    bvh = folder / f"take_{convention}.bvh"
    names = write_convention(bvh, clip.motion, convention)
    _recording(folder, clip, bvh)
    with gesturedb.open(clip.ref) as ref, gesturedb.build([folder], tmp_path / "db.h5", graph=False) as db:
        rec = db.recordings[0]
        assert rec.source_fps == CONVENTIONS[convention]["fps"]
        assert db.skeleton.length_unit_m == 0.01  # guessed from the height: centimetres
        assert "centimetres" in db.pairing.notes[0] and "guessed" in db.pairing.notes[0]
        assert db.n_frames == ref.n_frames
        # the feature joints were found by name in every scheme
        assert {r: names[ref.feature_joints[r]] for r in ref.feature_joints} == db.feature_joints
        np.testing.assert_allclose(db.pose_features, ref.pose_features, atol=2e-5)
        np.testing.assert_array_equal(db.audio_features, ref.audio_features)
        for k in ref.controls:
            np.testing.assert_allclose(db.controls[k], ref.controls[k], atol=2e-4, err_msg=k)
        np.testing.assert_array_equal(db.chunks.start, ref.chunks.start)
        np.testing.assert_array_equal(db.clips.start, ref.clips.start)
        assert list(db.words.text) == list(ref.words.text)
        idx = [db.joint_names.index(names[n]) for n in ref.joint_names]
        np.testing.assert_allclose(db.joint_positions[:, idx], ref.joint_positions, atol=2e-5)
        # the same speech finds the same windows in either database
        a = Searcher(ref).synthesize(clip.wav, repeat_guard_s=0)
        b = Searcher(db).synthesize(clip.wav, repeat_guard_s=0)
        np.testing.assert_array_equal(a.source_frames, b.source_frames)


def test_genea_files_have_six_channels_on_every_joint(clip, tmp_path):
    write_convention(tmp_path / "g.bvh", clip.motion[:30], "genea")
    text = (tmp_path / "g.bvh").read_text()
    hier = text.split("MOTION")[0]
    assert hier.count("CHANNELS 6") == hier.count("JOINT") + 1 and "CHANNELS 3" not in hier
    assert hier.splitlines()[1] == "ROOT body_world"
    m = read_bvh(tmp_path / "g.bvh")
    assert m.skeleton.names[:2] == ["body_world", "b_root"]


def test_zeggs_end_helpers_and_zyx_channels(clip, tmp_path):
    write_convention(tmp_path / "z.bvh", clip.motion[:30], "zeggs")
    m = read_bvh(tmp_path / "z.bvh")
    ends = [n for n in m.skeleton.names if n.endswith("End")]
    assert "HeadEnd" not in ends and "JawEnd" in ends and "LeftHandIndexEnd" in ends
    assert set(m.skeleton.channel_orders[1:]) == {"ZYX"}
    # mirroring pairs the helpers too
    perm = m.skeleton.mirror_permutation()
    i = m.skeleton.index("LeftHandIndexEnd")
    assert m.skeleton.names[perm[i]] == "RightHandIndexEnd"


# --- units ---------------------------------------------------------------------------------

def test_unit_guessed_from_height_for_every_common_unit(clip, tmp_path):
    m = clip.motion[:5]
    for unit in (1.0, 0.01, 0.001, 0.0254):
        write_bvh(tmp_path / "u.bvh", m, length_unit_m=unit)
        back = read_bvh(tmp_path / "u.bvh")
        assert back.skeleton.length_unit_m == unit
        np.testing.assert_allclose(back.skeleton.rest_height(), m.skeleton.rest_height(), rtol=1e-5)


def test_foreign_take_reads_as_inches_and_the_report_says_so(data_dir):
    path = data_dir / "bvh-foreign/AV_8Walk_Meredith_HVHA_Rep1.bvh"
    m = read_bvh(path)
    assert m.skeleton.length_unit_m == 0.0254
    text = describe_length_unit(m.skeleton)
    assert text.startswith("inches (0.0254 m per unit): the skeleton is 60.56 units = 1.54 m tall")
    assert "0.61 m in centimetres" in text
    # a walking adult: the head joint 1.2-1.5 m above the lowest toe in every frame (0.5 m in centimetres)
    height = np.ptp(m.positions[:, :, 1], axis=1)
    assert 1.2 < height.min() and height.max() < 1.5


def test_upper_body_skeleton_keeps_centimetres():
    # 60 units from pelvis to head and no legs: 0.6 m in centimetres is a plausible upper body
    names = ["Hips", "Spine", "Neck", "Head", "LeftArm", "LeftForeArm", "LeftHand"]
    parents = np.array([-1, 0, 1, 2, 1, 4, 5])
    offsets = np.array([[0, 0, 0], [0, 25, 0], [0, 20, 0], [0, 15, 0], [15, 20, 0], [28, 0, 0], [25, 0, 0]], float)
    assert guess_length_unit(offsets, parents, names) == 0.01
    # 60 units from foot to head with legs: 0.6 m is no standing adult, 1.52 m in inches is
    names2 = names + ["LeftUpLeg", "LeftLeg", "LeftFoot"]
    parents2 = np.concatenate([parents, [0, 7, 8]])
    offsets2 = np.concatenate([offsets * [1, 0.5, 1], [[5, -3, 0], [0, -14, 0], [0, -13, 0]]])
    assert guess_length_unit(offsets2, parents2, names2) == 0.0254
    assert guess_length_unit(offsets2 * 2.54, parents2, names2) == 0.01  # the same person in centimetres


def test_length_unit_names_and_numbers():
    assert parse_length_unit("cm") == 0.01 and parse_length_unit("inch") == 0.0254
    assert parse_length_unit("Metres") == 1.0 and parse_length_unit("0.3048") == 0.3048
    for bad in ("furlong", "0", "-1", "nan"):
        with pytest.raises(ParameterError, match="length unit: expected one of m, cm, mm, in"):
            parse_length_unit(bad)


def test_cli_length_unit_overrides_the_guess(data_dir, tmp_path, capsys):
    from gesturedb.cli.main import main

    d = tmp_path / "walk"
    d.mkdir()
    os.symlink(data_dir / "bvh-foreign/AV_8Walk_Meredith_HVHA_Rep1.bvh", d / "walk.bvh")
    sf.write(d / "walk.wav", np.zeros(int(16000 * 8.9), np.float32), 16000)
    mapping = ('{"left_index1": "LeftHandThumb1", "right_index1": "RightHandThumb1", '
               '"left_pinky1": "LeftHand_End", "right_pinky1": "RightHand_End"}')
    assert main(["build", str(d), "-o", str(tmp_path / "in.h5"), "--joint-map", mapping, "--no-graph"]) == 0
    err = capsys.readouterr().err
    assert err.count("unit: walk.bvh: guessed inches (0.0254 m per unit): the skeleton is 60.56 units = 1.54 m") == 1
    assert "--length-unit overrides" in err
    assert main(["build", str(d), "-o", str(tmp_path / "cm.h5"), "--joint-map", mapping, "--no-graph",
                 "--length-unit", "cm"]) == 0
    err = capsys.readouterr().err
    assert "unit: walk.bvh: given centimetres (0.01 m per unit): the skeleton is 60.56 units = 0.61 m tall" in err
    with gesturedb.open(tmp_path / "in.h5") as a, gesturedb.open(tmp_path / "cm.h5") as b:
        assert a.skeleton.length_unit_m == 0.0254 and b.skeleton.length_unit_m == 0.01
        np.testing.assert_allclose(a.joint_positions, b.joint_positions * 2.54, rtol=1e-5, atol=1e-6)
    assert main(["build", str(d), "-o", str(tmp_path / "x.h5"), "--length-unit", "furlong"]) == 2
    assert "length unit: expected one of" in capsys.readouterr().err


# --- mirroring a captured (asymmetric) skeleton ---------------------------------------------

def _lopsided(motion: Motion, factor: float) -> Motion:
    """The same motion on a skeleton whose left-side bones are ``factor`` times as long."""
    sk = motion.skeleton
    off = sk.offsets.copy()
    left = [j for j, n in enumerate(sk.names) if n.startswith("left_")]
    off[left] *= factor
    skel = Skeleton(sk.names, sk.parents, off, sk.channel_orders, sk.end_sites, sk.length_unit_m)
    return Motion(skel, motion.fps, motion.rotations, motion.root_positions)


def _reflected_error(motion: Motion, mirrored: Motion) -> float:
    """Largest distance between the mirrored copy and the reflected, side-swapped original, metres."""
    perm = motion.skeleton.mirror_permutation()
    want = motion.positions[:, perm] * np.array([-1.0, 1.0, 1.0])
    return float(np.abs(mirrored.positions - want).max())


def test_mirror_keeps_the_captured_skeleton_and_swaps_rotations(clip):
    m = clip.motion[::10]
    sym, note = mirrored_copy(m, "x.bvh")
    assert note is None and sym.skeleton is m.skeleton
    assert _reflected_error(m, sym) < 1e-9  # a symmetric skeleton mirrors exactly
    errs = {}
    for f in (1.02, 1.04):
        lop = _lopsided(m, f)
        mm, note = mirrored_copy(lop, "x.bvh")
        assert mm.skeleton is lop.skeleton  # the captured bones are kept
        assert f"left/right bones differ by up to {(f - 1) / f:.1%}" in note
        assert "keeps the captured skeleton and swaps the rotations" in note
        np.testing.assert_array_equal(mm.mirror().rotations, lop.rotations)  # swapping back gives the take
        errs[f] = _reflected_error(lop, mm)
    # the positions differ from a true reflection by about the asymmetry times the body's reach
    reach = float(np.linalg.norm(m.positions - m.positions[:, :1], axis=-1).max())
    assert errs[1.04] < 2 * 0.04 * reach
    assert 1.6 < errs[1.04] / errs[1.02] < 2.4


def test_mirror_refuses_only_a_skeleton_without_pairs():
    skel = Skeleton(["root", "spine", "head", "arm_a", "arm_b"], np.array([-1, 0, 1, 1, 1]),
                    np.array([[0, 1, 0], [0, 0.3, 0], [0, 0.3, 0], [0.2, 0.2, 0], [-0.25, 0.2, 0]]), ["ZXY"] * 5)
    m = Motion(skel, 30, np.tile([1.0, 0, 0, 0], (3, 5, 1)), np.zeros((3, 3)))
    with pytest.raises(InputFileError, match=r"x.bvh: mirror: expected left/right joint pairs .* got none among "
                                             r"the 5 joints \(root, spine, head, arm_a, arm_b\); build without"):
        mirrored_copy(m, "x.bvh")


@pytest.mark.slow
def test_build_mirrors_an_asymmetric_take(clip, tmp_path):
    folder = tmp_path / "lop"
    folder.mkdir()
    write_bvh(folder / "lop.bvh", _lopsided(clip.motion, 1.03), length_unit_m=0.01)
    _recording(folder, clip, folder / "lop.bvh")
    with gesturedb.build([folder], tmp_path / "m.h5", mirror=True, graph=False) as db:
        assert [r.name for r in db.recordings] == ["lop", "lop~mirror"]
        assert any("left/right bones differ by up to 2.9%" in n for n in db.pairing.notes)
        a, b = db.recordings
        P = db.joint_positions
        lw, rw = db.joint_names.index("left_wrist"), db.joint_names.index("right_wrist")
        # the mirrored performer's left wrist follows the reflected right wrist, off by the bone differences
        d = np.abs(P[b.start_frame:b.stop_frame, lw] - P[:a.n_frames, rw] * np.array([-1, 1, 1]))
        assert d.max() < 0.025 and np.median(d) < 0.02  # 1.8 cm at most on this take (1.2 cm with 2 %)
        # the mirrored copy's left-wrist height control is the original's right one, near enough
        np.testing.assert_allclose(db.controls["left_wrist_height"][b.start_frame:b.stop_frame],
                                   db.controls["right_wrist_height"][:a.n_frames], atol=0.05)


# --- speakers ---------------------------------------------------------------------------------

def test_speaker_only_from_known_naming_schemes(tmp_path):
    def src(stem, folder="alice"):
        return RecordingSource(stem, str(tmp_path / folder / f"{stem}.bvh"), "a.wav", None)

    assert infer_speaker(src("2_scott_0_1_1")) == "scott"  # BEAT: <id>_<name>_<type>_<start>_<end>
    assert infer_speaker(src("067_Speech_2_x_1_0")) == "alice"  # not BEAT: the folder
    assert infer_speaker(src("take_01")) == "alice"
    assert infer_speaker(RecordingSource("2_scott_0_1_1", "x.bvh", "a.wav", None, speaker="bob")) == "bob"


def test_pairing_file(tmp_path, clip):
    d = tmp_path / "takes"
    d.mkdir()
    for stem in ("a", "b"):
        os.link(clip.wav, d / f"{stem}.wav")
        (d / f"{stem}.bvh").write_text("x")
    (tmp_path / "pairs.csv").write_text("motion,audio,speaker,name\ntakes/a.bvh,takes/a.wav,anna,first\n"
                                        "takes/b.bvh,takes/b.wav,,\n")
    a, b = read_pairing_file(tmp_path / "pairs.csv")
    assert (a.name, a.speaker, a.transcript) == ("first", "anna", None)
    assert a.motion == str(tmp_path / "takes/a.bvh") and (b.name, b.speaker) == ("b", None)
    # Excel's "CSV UTF-8" starts with a byte order mark: the header still reads "motion"
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "pairs.csv").read_bytes())
    assert [r.name for r in read_pairing_file(tmp_path / "bom.csv")] == ["first", "b"]
    (tmp_path / "bad.csv").write_text("motion,sound\nx.bvh,x.wav\n")
    with pytest.raises(InputFileError, match="bad.csv: line 1: header: expected the columns motion, audio"):
        read_pairing_file(tmp_path / "bad.csv")
    (tmp_path / "missing.csv").write_text("motion,audio\ntakes/a.bvh,takes/zzz.wav\n")
    with pytest.raises(InputFileError, match="missing.csv: line 2: audio: no such file"):
        read_pairing_file(tmp_path / "missing.csv")


@pytest.mark.slow
def test_two_speakers_and_synth_speaker(clip, scott_dir, tmp_path, capsys):
    from gesturedb.cli.main import main

    # speaker 1: the clip under a non-BEAT name in a folder called "anna" (name: folder)
    anna = tmp_path / "anna"
    anna.mkdir()
    write_bvh(anna / "067_Speech_2_x_1_0.bvh", clip.motion, length_unit_m=0.01)
    _recording(anna, clip, anna / "067_Speech_2_x_1_0.bvh")
    # speaker 2: the same clip mirrored, named by a pairing file
    other = tmp_path / "other"
    other.mkdir()
    write_bvh(other / "take.bvh", clip.motion.mirror(), length_unit_m=0.01)
    _recording(other, clip, other / "take.bvh")
    (tmp_path / "pairs.csv").write_text("motion,audio,transcript,speaker\nother/take.bvh,other/take.wav,"
                                        "other/take.tsv,Bea\n")
    db_path = tmp_path / "two.h5"
    assert main(["build", str(anna), "--pairs", str(tmp_path / "pairs.csv"), "-o", str(db_path), "--no-graph"]) == 0
    err = capsys.readouterr().err
    assert "take: take.bvh + take.wav + take.tsv (speaker Bea)" in err
    with gesturedb.open(db_path) as db:
        assert {r.name: r.speaker for r in db.recordings} == {"067_Speech_2_x_1_0": "anna", "take": "Bea"}
    out = tmp_path / "bea.bvh"
    assert main(["synth", str(db_path), "--audio", str(clip.wav), "--speaker", "Bea", "-o", str(out)]) == 0
    import json

    prov = json.loads((tmp_path / "bea.provenance.json").read_text())
    assert prov["options"]["speaker"] == "Bea"
    assert {s["recording"] for s in prov["steps"]} == {"take"}
    assert main(["synth", str(db_path), "--audio", str(clip.wav), "--speaker", "anna", "-o", str(out)]) == 0
    prov = json.loads((tmp_path / "bea.provenance.json").read_text())
    assert {s["recording"] for s in prov["steps"]} == {"067_Speech_2_x_1_0"}
    assert main(["synth", str(db_path), "--audio", str(clip.wav), "--speaker", "zed", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "speaker: no recording of speaker 'zed'" in err and "speakers: Bea, anna" in err
    # --speaker on the build names every recording that does not name its own
    assert main(["build", str(anna), "--pairs", str(tmp_path / "pairs.csv"), "-o", str(db_path), "--no-graph",
                 "--speaker", "Cy", "-q"]) == 0
    with gesturedb.open(db_path) as db:
        assert {r.name: r.speaker for r in db.recordings} == {"067_Speech_2_x_1_0": "Cy", "take": "Bea"}
