"""scripts/setup.sh: a project-local .venv unless one is active, every declared extra, no reinstall when nothing changed.

The script runs for real on a copy of the files it reads (setup.py, pyproject.toml,
csrc/), with a stand-in ``python3`` first on the PATH that logs every call, creates
"virtual environments" as folders and answers ``-m pip`` without installing (printing
``$PIP_OUTPUT`` and exiting ``$PIP_EXIT`` when given); everything else it hands to the
real interpreter (so setup.py's extras are parsed for real). scripts/blender.sh, which
installs Blender's bpy for tests/test_blender.py, runs the same way.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FAKE = """#!/usr/bin/env bash
echo "$0 $*" >> "$SETUP_LOG"
if [ "$1" = "-m" ] && [ "$2" = "venv" ]; then mkdir -p "$3/bin"; cp "$0" "$3/bin/python"; exit 0; fi
if [ "$1" = "-m" ] && [ "$2" = "pip" ]; then
  [ -n "${{PIP_OUTPUT:-}}" ] && cat "$PIP_OUTPUT"
  exit "${{PIP_EXIT:-0}}"
fi
exec {real} "$@"
"""


@pytest.fixture()
def project(tmp_path):
    if shutil.which("sha256sum") is None or shutil.which("dpkg") is None:
        pytest.skip("setup.sh needs sha256sum and dpkg (Debian)")
    proj = tmp_path / "proj"
    (proj / "scripts").mkdir(parents=True)
    for f in ("scripts/setup.sh", "scripts/venv.sh", "scripts/pip_install.sh", "scripts/blender.sh", "setup.py",
              "pyproject.toml"):
        shutil.copy(ROOT / f, proj / f)
    shutil.copytree(ROOT / "csrc", proj / "csrc")
    fake_bin = tmp_path / "bin"
    fake_bin.mkdir()
    (fake_bin / "python3").write_text(FAKE.format(real=sys.executable))
    (fake_bin / "python3").chmod(0o755)
    log = tmp_path / "log"
    log.write_text("")
    env = {k: v for k, v in os.environ.items() if k != "VIRTUAL_ENV"}
    env.update(PATH=f"{fake_bin}{os.pathsep}{env['PATH']}", SETUP_LOG=str(log))

    def run(script="scripts/setup.sh", *args, ok=True, **more):
        before = log.read_text()
        r = subprocess.run(["bash", script, *args], cwd=proj, env={**env, **more}, capture_output=True,
                           text=True, timeout=120)
        assert (r.returncode == 0) == ok, r.stderr
        return r.stderr, log.read_text()[len(before):]

    return proj, run


def _pip_calls(calls: str) -> list[str]:
    return [c for c in calls.splitlines() if " -m pip install" in c and "bpy" not in c]


def test_setup_uses_a_local_venv_and_skips_an_unchanged_install(project):
    proj, run = project
    tests = ("scripts/setup.sh", "--tests")
    err, calls = run(*tests)
    venv = proj / ".venv"
    assert f"-m venv {venv}" in calls and (venv / "bin/python").exists()
    pip = _pip_calls(calls)
    # into the project's environment, with every extra setup.py declares (test, refiner, docs, serve today)
    assert len(pip) == 1 and pip[0].startswith(f"{venv}/bin/python -m pip install")
    extras = sorted(re.findall(r'^        "(\w+)": \[', (proj / "setup.py").read_text(), re.M))
    assert {"refiner", "test"} <= set(extras) and pip[0].endswith(f"-e .[{','.join(extras)}]")
    assert (venv / ".gesturedb-install-stamp").exists()
    # nothing changed: no pip, and it says so
    err, calls = run(*tests)
    assert _pip_calls(calls) == [] and "up to date" in err and "-m venv" not in calls
    # a changed C++ source, or setup.py, installs again
    src = sorted((proj / "csrc").glob("*.cpp"))[0]
    src.write_text(src.read_text() + "\n// changed\n")
    assert len(_pip_calls(run(*tests)[1])) == 1
    assert _pip_calls(run(*tests)[1]) == []
    setup = proj / "setup.py"
    setup.write_text(setup.read_text().replace('"refiner": ["torch==2.13.0"],',
                                               '"refiner": ["torch==2.13.0"],\n        "aaa": [],'))
    assert _pip_calls(run(*tests)[1])[0].endswith(f"-e .[{','.join(['aaa'] + extras)}]")
    # without --tests (the demo), only the product's own extras: no pytest, docs tools or torch
    assert _pip_calls(run()[1])[0].endswith("-e .[serve]")


def test_setup_uses_an_active_virtualenv(project, tmp_path):
    proj, run = project
    mine = tmp_path / "mine"
    (mine / "bin").mkdir(parents=True)
    shutil.copy(tmp_path / "bin/python3", mine / "bin/python")
    err, calls = run(VIRTUAL_ENV=str(mine))
    pip = _pip_calls(calls)
    assert len(pip) == 1 and pip[0].startswith(f"{mine}/bin/python -m pip install")
    assert not (proj / ".venv").exists()


def test_setup_never_installs_blender_and_test_sh_does(project):
    """bpy (about 1 GB) is for tests/test_blender.py alone: the test command installs it, the demo does not."""
    proj, run = project
    err, calls = run()
    assert "bpy" not in calls and "venv-blender" not in calls and not (proj / ".venv-blender").exists()
    test_sh = (ROOT / "scripts/test.sh").read_text()
    assert "bash scripts/blender.sh" in test_sh
    assert test_sh.index("bash scripts/blender.sh") < test_sh.index("pytest")
    assert "blender" not in (ROOT / "scripts/demo.sh").read_text()


def test_blender_script_installs_bpy_once_or_says_why_not(project, tmp_path):
    proj, run = project
    err, calls = run("scripts/blender.sh")
    if sys.version_info[:2] != (3, 11):
        assert "bpy needs Python 3.11" in err and "-m pip" not in calls
        return
    venv = proj / ".venv-blender"
    assert "-m venv .venv-blender" in calls
    pip = [c for c in calls.splitlines() if " -m pip install" in c]
    assert len(pip) == 1 and pip[0].startswith(".venv-blender/bin/python -m pip install") and "bpy>=4.2,<6" in pip[0]
    assert "installing bpy (about 1 GB) into .venv-blender" in err and venv.is_dir()
    # pip fails (no network, no wheel for this platform): it says so, and the test command goes on
    out = tmp_path / "pip.out"
    out.write_text("ERROR: Could not find a version that satisfies the requirement bpy<6,>=4.2\n")
    err, calls = run("scripts/blender.sh", PIP_OUTPUT=str(out), PIP_EXIT="1")
    assert "blender: pip failed (exit 1)" in err and "Could not find a version" in err
    assert err.strip().endswith("bpy did not install; tests/test_blender.py will be skipped")
    # another interpreter with bpy: nothing to install
    err, calls = run("scripts/blender.sh", GESTUREDB_BLENDER_PYTHON="/opt/blender/python")
    assert "-m pip" not in calls and "nothing to install" in err


PIP_OUTPUT = """Obtaining file:///proj
  Installing build dependencies: started
  Installing build dependencies: finished with status 'done'
Collecting numpy>=1.24 (from gesturedb==0.1)
  Downloading numpy-2.1.0-cp311-cp311-manylinux_2_17_x86_64.whl.metadata (60 kB)
  Downloading numpy-2.1.0-cp311-cp311-manylinux_2_17_x86_64.whl (16.3 MB)
     |################################| 16.3 MB 50 MB/s
Collecting torch==2.13.0 (from gesturedb==0.1)
  Downloading https://mirror.example/whl/cpu/torch-2.13.0%2Bcpu-cp311-cp311-linux_x86_64.whl (190.4 MB)
""" + "".join(f"Requirement already satisfied: dep{i} in ./.venv/lib/python3.11/site-packages (1.0)\n"
              for i in range(300)) + """  Using cached scipy-1.14.0-cp311-cp311-manylinux_2_17_x86_64.whl (41.2 MB)
WARNING: Location 'file:///opt/pypi-more/simple/six/' is ignored: it is neither a file nor a directory.
Processing /no/such/index/six-1.17.0-py2.py3-none-any.whl
Processing {wheels}/tqdm-4.70.1-py3-none-any.whl
Building wheels for collected packages: gesturedb
  Building editable for gesturedb (pyproject.toml): started
  Building editable for gesturedb (pyproject.toml): finished with status 'done'
  Created wheel for gesturedb: filename=gesturedb-0.1-0.editable-cp311-cp311-linux_x86_64.whl size=9000
Successfully built gesturedb
Installing collected packages: numpy, torch, scipy, gesturedb
Successfully installed gesturedb-0.1 numpy-2.1.0 scipy-1.14.0 torch-2.13.0
"""


def test_setup_shows_a_line_per_download_not_pips_flood(project, tmp_path):
    proj, run = project
    out = tmp_path / "pip.out"
    (tmp_path / "tqdm-4.70.1-py3-none-any.whl").write_bytes(b"x" * 2_600_000)  # a local index's wheel
    out.write_text(PIP_OUTPUT.replace("{wheels}", str(tmp_path)))
    err, calls = run(PIP_OUTPUT=str(out))
    lines = err.strip().splitlines()
    assert lines[0].startswith("setup: creating the virtual environment")
    lines = lines[1:]
    assert "the first time up to 2.6 GB" in lines[0]  # what is coming and why it takes minutes
    shown = [re.sub(r"^setup: +\d+:\d\d  ", "", ln) for ln in lines[1:-1]]
    assert shown == [
        "Downloading numpy-2.1.0-cp311-cp311-manylinux_2_17_x86_64.whl (16.3 MB)",
        "Downloading torch-2.13.0%2Bcpu-cp311-cp311-linux_x86_64.whl (190.4 MB)",
        "Using cached scipy-1.14.0-cp311-cp311-manylinux_2_17_x86_64.whl (41.2 MB)",
        "Processing six-1.17.0-py2.py3-none-any.whl",
        "Processing tqdm-4.70.1-py3-none-any.whl (3 MB)",
        "Building wheels for collected packages: gesturedb",
        "Building editable for gesturedb (pyproject.toml): started",
        "Building editable for gesturedb (pyproject.toml): finished with status 'done'",
        "Successfully built gesturedb",
        "installing 4 packages",
    ], lines
    assert re.fullmatch(r"setup: done in \d+ min \d+ s", lines[-1])
    assert "--progress-bar off" in _pip_calls(calls)[0]  # bars are what floods a CI log
    # pip fails: the end of its output, and setup fails without writing its stamp
    (proj / "setup.py").write_text((proj / "setup.py").read_text() + "\n# changed\n")
    out.write_text("Collecting nope\nERROR: No matching distribution found for nope\n")
    err, _ = run(ok=False, PIP_OUTPUT=str(out), PIP_EXIT="1")
    assert "setup: pip failed (exit 1)" in err and err.strip().endswith("No matching distribution found for nope")
    assert not (proj / ".venv" / ".gesturedb-install-stamp").exists()
