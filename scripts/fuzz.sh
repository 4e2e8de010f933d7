#!/usr/bin/env bash
# Long fuzz runs of every parser (not in CI; CI runs each target for a few seconds in tests/test_fuzz.py).
#   scripts/fuzz.sh [SECONDS_PER_TARGET=300] [TARGET...]     targets: bvh transcripts expression npz gltf checkpoint
# Corpora grow in fuzz-corpus/<target>/ (git-ignored); crashes are written as fuzz-corpus/crash-*.
# A crash is any exception other than GestureDBError: reproduce with python tests/fuzz/fuzz_<t>.py CRASH_FILE
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${1:-300}
shift || true
targets=("$@")
[ ${#targets[@]} -gt 0 ] || targets=(bvh transcripts expression npz gltf checkpoint)
python -c "import atheris" 2>/dev/null || { echo "fuzz.sh: atheris is not installed: pip install atheris" >&2; exit 2; }
mkdir -p fuzz-corpus
status=0
for t in "${targets[@]}"; do
    mkdir -p "fuzz-corpus/$t"
    echo "== $t: ${secs}s" >&2
    OMP_NUM_THREADS=1 python "tests/fuzz/fuzz_$t.py" -max_total_time="$secs" -artifact_prefix=fuzz-corpus/ \
        "fuzz-corpus/$t" || { echo "== $t: FOUND A CRASH (see fuzz-corpus/crash-*)" >&2; status=1; }
done
exit $status
