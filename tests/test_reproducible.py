"""The same recordings give the same database, and the same synthesis, on every x86 CPU.

numpy picks its implementations of ``log``, of ``abs`` of complex numbers and others by CPU
(AVX-512, AVX2 or SSE, each rounding its own way), and OpenBLAS picks its matrix-product kernels
the same way. The build and the synthesis avoid every such choice (the audio features' own
logarithm and ``re^2 + im^2``, the motion graph's exact products, the style model's numpy
Cholesky), so that a database does not depend on the machine, or on the Dask worker, that
built it; gesturedb's own search kernels (scalar, AVX2, AVX-512, also picked by CPU) sum in one
order. Other CPUs are emulated with ``NPY_DISABLE_CPU_FEATURES``, ``OPENBLAS_CORETYPE`` and
``GESTUREDB_SIMD`` in subprocesses; controls check that those really switch implementations.
"""
from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

try:  # tests/ is on sys.path when it is not a package, the repo root when it is
    from dbcontent import differing
except ModuleNotFoundError:  # pragma: no cover
    from tests.dbcontent import differing

# each run: build (no mirror) from the real recording, a k-NN and a graph synthesis of one input,
# then what numpy and OpenBLAS picked on this "CPU"
_SCRIPT = """
import hashlib, sys
import numpy as np
from numpy.lib.introspect import opt_func_info
from gesturedb.cli.main import main
data, out = sys.argv[1], sys.argv[2]
inp = data + "/inputs/2_scott_0_2_2"
assert main(["build", data, "-o", out + "/db.h5", "-q"]) == 0
for method in ("knn", "graph"):
    assert main(["synth", out + "/db.h5", "--method", method, "--audio", inp + ".wav", "--transcript",
                 inp + ".TextGrid", "-o", out + f"/{method}.bvh", "--npz", out + f"/{method}.npz"]) == 0
x = np.random.default_rng(0).standard_normal((300, 700), dtype=np.float32)
from gesturedb import search
print(opt_func_info(func_name="^log$", signature="float64")["log"]["dd"]["current"],
      hashlib.sha256((x @ x.T).tobytes()).hexdigest(), search.get_simd())
"""

_ENV = ("NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE", "GESTUREDB_SIMD")
CPUS = {
    "this machine": {},
    "AVX2": {"NPY_DISABLE_CPU_FEATURES": "X86_V4", "OPENBLAS_CORETYPE": "Haswell", "GESTUREDB_SIMD": "avx2"},
    "SSE4": {"NPY_DISABLE_CPU_FEATURES": "X86_V4 X86_V3", "OPENBLAS_CORETYPE": "Prescott",
             "GESTUREDB_SIMD": "scalar"},
}


def test_build_and_synthesis_are_the_same_bits_on_every_x86_cpu(scott_dir, tmp_path):
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("the emulated CPUs are x86 ones")
    from gesturedb import search

    runs = {}
    for cpu, env_extra in CPUS.items():
        out = tmp_path / cpu.replace(" ", "_")
        out.mkdir()
        env = {k: v for k, v in os.environ.items() if k not in _ENV}
        env.update(env_extra)
        if env.get("GESTUREDB_SIMD") not in (None, *search.kernels()):
            env.pop("GESTUREDB_SIMD")  # a CPU without AVX2: its own kernel is the scalar one anyway
        r = subprocess.run([sys.executable, "-c", _SCRIPT, str(scott_dir), str(out)], env=env,
                           capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stderr[-3000:]
        runs[cpu] = (out, r.stdout.strip().splitlines()[-1].split())
    # controls: each emulated CPU really ran other numpy and OpenBLAS code
    targets = {cpu: v[1][0] for cpu, v in runs.items()}
    blas = {cpu: v[1][1] for cpu, v in runs.items()}
    assert targets["AVX2"] == "X86_V3" and targets["SSE4"].startswith("baseline"), targets
    assert blas["AVX2"] != blas["SSE4"], "OPENBLAS_CORETYPE did not change the kernel"
    simd = {cpu: v[1][2] for cpu, v in runs.items()}
    assert simd["SSE4"] == "scalar" and simd["AVX2"] in ("avx2", "scalar"), simd

    ref_dir = runs["this machine"][0]
    for cpu in ("AVX2", "SSE4"):
        out = runs[cpu][0]
        assert differing(ref_dir / "db.h5", out / "db.h5") == [], cpu
        for name in ("knn.bvh", "graph.bvh", "knn.npz", "graph.npz"):
            assert (out / name).read_bytes() == (ref_dir / name).read_bytes(), f"{cpu}: {name}"
