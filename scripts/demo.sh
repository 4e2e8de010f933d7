#!/usr/bin/env bash
# The main job: build a database from the BEAT2 speaker and synthesize gestures
# for held-out speech. Outputs go to out/ (not tracked).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${GESTUREDB_DATA:-../shared/data}
bash scripts/setup.sh
. scripts/venv.sh  # the environment setup.sh installed into
mkdir -p out
gesturedb build "$DATA/beat2-scott" -o out/scott.h5 --mirror
gesturedb info out/scott.h5
# a keyword sub-database: whenever the speech says "time", gestures come from the speaker's own "time"s
gesturedb keywords out/scott.h5 add time --replace
gesturedb synth out/scott.h5 \
    --audio "$DATA/beat2-scott/inputs/2_scott_0_2_2.wav" \
    --transcript "$DATA/beat2-scott/inputs/2_scott_0_2_2.TextGrid" \
    -o out/2_scott_0_2_2.bvh --npz out/2_scott_0_2_2.npz --render out/2_scott_0_2_2.mp4
echo "demo: outputs in out/"
