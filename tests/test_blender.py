"""Our .glb and .bvh in real Blender (the `bpy` module from PyPI), through Blender's own importers.

bpy pins numpy < 2 and needs Python 3.11, so it lives in an environment of its own
(`.venv-blender`, made by scripts/blender.sh, which scripts/test.sh runs); the test runs tests/blender_check.py there
and compares what Blender computes with our forward kinematics. Where bpy cannot be
installed the test is skipped and says why. GESTUREDB_BLENDER_PYTHON names another
interpreter that has bpy; GESTUREDB_BLENDER_PICTURE=path keeps the rendered picture
(docs/img/blender.png was made so).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rigs
from gesturedb.io import read_motion, write_motion
from gesturedb.retarget import load_rig, retarget

ROOT = Path(__file__).resolve().parents[1]
CHECK = Path(__file__).with_name("blender_check.py")


def _blender_python() -> str:
    exe = os.environ.get("GESTUREDB_BLENDER_PYTHON") or str(ROOT / ".venv-blender" / "bin" / "python")
    if not Path(exe).exists():
        pytest.skip(f"Blender's bpy is not installed: no {exe} (scripts/blender.sh makes it with `pip install bpy`, "
                    f"which needs Python 3.11; this is Python {sys.version_info[0]}.{sys.version_info[1]})")
    probe = subprocess.run([exe, "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True, text=True,
                           timeout=300)
    if probe.returncode != 0:
        pytest.skip(f"Blender's bpy does not import in {exe}: {probe.stderr.strip().splitlines()[-1:]}")
    return exe


@pytest.mark.slow
def test_blender_imports_our_glb_and_bvh(scott_dir, tmp_path):
    exe = _blender_python()
    source = read_motion(scott_dir / "2_scott_0_1_1.npz")[900:1200]
    rig_bvh = tmp_path / "mixamo.bvh"
    rig_bvh.write_text(rigs.mixamo_rig())  # A-pose, centimetres, Mixamo names
    motion = retarget(source, load_rig(rig_bvh)).motion
    glb, bvh = tmp_path / "gesture.glb", tmp_path / "gesture.bvh"
    write_motion(glb, motion)
    write_motion(bvh, motion)
    frames = [0, 37, 150, 299]
    # the picture shows the frame where the hands are highest: a gesture, not a rest pose
    hands = [motion.skeleton.index(n) for n in ("mixamorig:LeftHand", "mixamorig:RightHand")]
    shown = int(np.argmax(motion.positions[:, hands, 1].max(axis=1)))
    bones = ["mixamorig:LeftHand", "mixamorig:RightHand", "mixamorig:LeftForeArm", "mixamorig:Head"]
    out = tmp_path / "blender.json"
    png = tmp_path / "blender.png"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONNOUSERSITE="1")
    env.pop("PYTHONPATH", None)
    run = subprocess.run(
        [exe, str(CHECK), "--glb", str(glb), "--bvh", str(bvh), "--bvh-scale", str(motion.skeleton.length_unit_m),
         "--fps", str(motion.fps), "--frames", ",".join(map(str, frames)), "--bones", ",".join(bones),
         "--out", str(out), "--render", str(png), "--render-frame", str(shown)],
        capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    got = json.loads(out.read_text())
    ours = motion.positions[frames]
    for kind in ("glb", "bvh"):
        for b in bones:
            err = np.abs(np.asarray(got[kind][b]) - ours[:, motion.skeleton.index(b)]).max()
            print(f"Blender {got['version']} {kind} {b}: max |ours - Blender| {err:.2e} m")
            # float32 in the .glb, 6 decimals of a centimetre in the .bvh
            assert err < 1e-3, (kind, b, err)
    # the user's step (docs/blender.md): the mesh bound to the rig follows the imported BVH armature
    print(f"mesh under the BVH armature vs under the glTF armature: max {got['mesh_swap_max_m']:.2e} m")
    assert got["mesh_swap_max_m"] < 1e-3
    # the wrists really move between the frames compared (so the check can fail)
    w = np.asarray(got["glb"]["mixamorig:LeftHand"])
    assert np.linalg.norm(w - w[0], axis=1).max() > 0.05
    assert png.stat().st_size > 10_000
    keep = os.environ.get("GESTUREDB_BLENDER_PICTURE")
    if keep:
        shutil.copy(png, keep)
