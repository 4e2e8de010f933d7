"""scripts/setup.sh: a project-local .venv unless one is active, every declared extra, no reinstall when nothing changed.

The script runs for real on a copy of the files it reads (setup.py, pyproject.toml,
csrc/), with a stand-in ``python3`` first on the PATH that logs every call, creates
"virtual environments" as folders and answers ``-m pip`` without installing; everything
else it hands to the real interpreter (so setup.py's extras are parsed for real).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FAKE = """#!/usr/bin/env bash
echo "$0 $*" >> "$SETUP_LOG"
if [ "$1" = "-m" ] && [ "$2" = "venv" ]; then mkdir -p "$3/bin"; cp "$0" "$3/bin/python"; exit 0; fi
if [ "$1" = "-m" ] && [ "$2" = "pip" ]; then exit 0; fi
exec {real} "$@"
"""


@pytest.fixture()
def project(tmp_path):
    if shutil.which("sha256sum") is None or shutil.which("dpkg") is None:
        pytest.skip("setup.sh needs sha256sum and dpkg (Debian)")
    proj = tmp_path / "proj"
    (proj / "scripts").mkdir(parents=True)
    for f in ("scripts/setup.sh", "scripts/venv.sh", "setup.py", "pyproject.toml"):
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

    def run(**more):
        before = log.read_text()
        r = subprocess.run(["bash", "scripts/setup.sh"], cwd=proj, env={**env, **more}, capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        return r.stderr, log.read_text()[len(before):]

    return proj, run


def _pip_calls(calls: str) -> list[str]:
    return [c for c in calls.splitlines() if " -m pip install" in c and "bpy" not in c]


def test_setup_uses_a_local_venv_and_skips_an_unchanged_install(project):
    proj, run = project
    err, calls = run()
    venv = proj / ".venv"
    assert f"-m venv {venv}" in calls and (venv / "bin/python").exists()
    pip = _pip_calls(calls)
    # into the project's environment, with every extra setup.py declares (test and refiner today)
    assert len(pip) == 1 and pip[0].startswith(f"{venv}/bin/python -m pip install")
    assert pip[0].endswith("-e .[refiner,test]")
    assert (venv / ".gesturedb-install-stamp").exists()
    # nothing changed: no pip, and it says so
    err, calls = run()
    assert _pip_calls(calls) == [] and "up to date" in err and "-m venv" not in calls
    # a changed C++ source, or setup.py, installs again
    src = sorted((proj / "csrc").glob("*.cpp"))[0]
    src.write_text(src.read_text() + "\n// changed\n")
    assert len(_pip_calls(run()[1])) == 1
    assert _pip_calls(run()[1]) == []
    setup = proj / "setup.py"
    setup.write_text(setup.read_text().replace('"refiner": ["torch==2.13.0"],',
                                               '"refiner": ["torch==2.13.0"],\n        "docs": [],'))
    assert _pip_calls(run()[1])[0].endswith("-e .[docs,refiner,test]")


def test_setup_uses_an_active_virtualenv(project, tmp_path):
    proj, run = project
    mine = tmp_path / "mine"
    (mine / "bin").mkdir(parents=True)
    shutil.copy(tmp_path / "bin/python3", mine / "bin/python")
    err, calls = run(VIRTUAL_ENV=str(mine))
    pip = _pip_calls(calls)
    assert len(pip) == 1 and pip[0].startswith(f"{mine}/bin/python -m pip install")
    assert not (proj / ".venv").exists()
