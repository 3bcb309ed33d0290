#!/usr/bin/env bash
# The benchmark sweep: run time against error for every method, side by side, then plots and a
# markdown summary. One command:
#   bench/sweep.sh quick [BUILD_DIR] [OUT_DIR]   # under 2 minutes (part of the README's main job)
#   bench/sweep.sh full  [BUILD_DIR] [OUT_DIR]   # the full sweep, within 30 minutes on 2 cores
# Real data sets come from ../shared/data (or BHCL_DATA_DIR) when present; rows for absent files
# are skipped with a message. Results: OUT_DIR/*.csv, OUT_DIR/*.png, OUT_DIR/summary.md.
set -euo pipefail
mode=${1:-quick}
build=${2:-build}
out=${3:-bench-results/$mode}
bench="$build/bench/knn_bench"
[ -x "$bench" ] || { echo "sweep: $bench not built (cmake --build $build)"; exit 1; }
mkdir -p "$out"
# FLANN answers with as many threads as PoCL has: both use every core unless told otherwise.
export POCL_MAX_PTHREAD_COUNT=${POCL_MAX_PTHREAD_COUNT:-$(nproc)}
run() { echo "+ knn_bench $*"; "$bench" "$@"; }
case "$mode" in
  quick)
    run --data uniform,cornell --N 100000 --queries 20000 --k 10,50 --A 2,4,8,16 \
        --presets auto --reps 3 --csv "$out/quick.csv"
    ;;
  full)
    # A and k sweeps at 1M on the generated and the real sets.
    run --data uniform,cornell --N 1000000 --queries 50000 --k 10,50,100 --A 1,2,4,8,16,32 \
        --presets auto,paper --methods blockhash,kdtree,flann --reps 3 --csv "$out/a_sweep.csv"
    run --data bunny,dragon,autzen --N 1000000 --queries 50000 --k 10,50,100 --A 1,2,4,8,16,32 \
        --presets auto --methods blockhash,kdtree,flann --reps 3 --csv "$out/real.csv"
    run --data autzen --N 2000000 --queries 50000 --k 10,50 --A 4,8,16 \
        --presets auto --methods blockhash,kdtree,flann --reps 3 --csv "$out/autzen2m.csv"
    # Hilbert-sorted queries against the caller's order.
    run --data uniform,cornell --N 1000000 --queries 50000 --k 50 --A 8 --sort both \
        --presets auto --methods blockhash,kdtree --reps 3 --csv "$out/sorted.csv"
    # N from 1e4 to 1e7 (brute force at small N only).
    run --data uniform,cornell --N 10000,100000 --queries 20000 --k 10,50 --A 4,8,16 \
        --presets auto --reps 3 --csv "$out/n_small.csv"
    run --data uniform,cornell --N 1000000,10000000 --queries 50000 --k 10,50 --A 4,8,16 \
        --presets auto --methods blockhash,kdtree,flann --reps 3 --csv "$out/n_large.csv"
    ;;
  *) echo "sweep: mode must be quick or full"; exit 2 ;;
esac
# Debian's python3 has python3-matplotlib; a python3 earlier on PATH (pyenv, venv) may not.
py=python3
if [ -x /usr/bin/python3 ] && /usr/bin/python3 -c "import matplotlib" 2>/dev/null; then py=/usr/bin/python3; fi
"$py" "$(dirname "$0")/plot.py" "$out"/*.csv --out "$out"
