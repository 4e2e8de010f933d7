"""Each atheris fuzz target of tests/fuzz/ runs for a few seconds (scripts/fuzz.sh runs them for long).

A target fails on any exception other than GestureDBError. Without atheris (it
builds only on some platforms) these tests are skipped with a warning that says
so, never silently.
"""
from __future__ import annotations

import os
import resource
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

FUZZ = Path(__file__).resolve().parent / "fuzz"
TARGETS = ["bvh", "transcripts", "expression", "npz", "gltf", "checkpoint"]
SECONDS = 3


def _atheris_missing() -> str | None:
    try:
        import atheris  # noqa: F401
    except ImportError as exc:
        return f"atheris is not installed ({exc}); the fuzz targets did NOT run (pip install atheris)"
    return None


@pytest.mark.parametrize("target", TARGETS)
def test_fuzz_target_finds_nothing_in_a_few_seconds(target, tmp_path):
    missing = _atheris_missing()
    if missing:
        warnings.warn(missing)
        pytest.skip(missing)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    # libFuzzer's memory limit (2 GB by default) is on the process's peak RSS, which Linux
    # carries over from this process through fork and exec: after a test that used 4 GB here,
    # every target stopped at once with "out-of-memory". The limit is 2 GB above that peak.
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024
    proc = subprocess.run(
        [sys.executable, str(FUZZ / f"fuzz_{target}.py"), f"-max_total_time={SECONDS}",
         f"-rss_limit_mb={peak_mb + 2048}", f"-artifact_prefix={tmp_path}/"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )
    # libFuzzer: exit 0 after max_total_time. On a Python exception atheris prints the traceback on
    # STDOUT and exits ("fuzz target exited" on stderr), so both go into the message, and the input
    # itself as hex: a CI run's tmp_path is gone by the time anyone reads the log.
    if proc.returncode != 0:
        found = sorted(tmp_path.glob("crash-*"))
        data = found[0].read_bytes() if found else b""
        shown = data.hex() if len(data) <= 4096 else f"{len(data)} bytes, too long to show"
        pytest.fail(f"fuzz_{target} found a crash (exit {proc.returncode}):\n--- stdout\n{proc.stdout[-3000:]}\n"
                    f"--- stderr\n{proc.stderr[-1500:]}\n--- input ({len(data)} bytes, hex)\n{shown}")
    assert "Done" in proc.stderr and " runs in " in proc.stderr, proc.stderr[-2000:]
    assert not list(tmp_path.glob("crash-*"))


@pytest.mark.parametrize("crash", sorted((FUZZ / "regressions").glob("*")), ids=lambda p: p.name)
def test_inputs_the_fuzzers_found_give_one_line_errors(crash):
    """Every crash a fuzzer found is kept here and must now be a GestureDBError naming the file."""
    from gesturedb.errors import InputFileError
    from gesturedb.io import read_motion, read_transcript

    reader = read_motion if crash.suffix in (".npz", ".bvh", ".glb", ".gltf") else read_transcript
    with pytest.raises(InputFileError, match=str(crash.name)) as info:
        reader(crash)
    assert "\n" not in str(info.value)
