#!/bin/sh
# Issue 36's "frame no slower, build <= 1.2x the filing's": the build and the photon-map frame of
# main at the filing (7f729ba, BEFORE_DIR = that tree's build/bench) against today's
# (build/bench), processes alternating, each run's block hashing figure taken as its ratio to the
# kd-tree in the same process (the kd-tree's code did not change between the two), so a load
# change between processes cancels. AVX-512, 2 threads. Then frame_build_ab.py summarises.
set -e
B=${BEFORE_DIR:-/work/base36/build/bench}
A=${AFTER_DIR:-build/bench}
OUT=${OUT:-bench/results/far/frame_build_rounds}
N=${ALTERNATIONS:-4}
export POCL_MAX_PTHREAD_COUNT=2
mkdir -p "$OUT"
i=1
while [ "$i" -le "$N" ]; do
  for side in before after; do
    if [ $side = before ]; then D=$B; else D=$A; fi
    "$D/build_bench" --data cornell,uniform,autzen --N 1000000 --methods blockhash,kdtree --rounds 5 \
      --data-dir "${BHCL_DATA_DIR:-../shared/data}" > "$OUT/build_${side}_$i.txt" 2>&1
    "$D/frame_bench" --rounds 3 --methods kdtree,blockhash > "$OUT/frame_${side}_$i.txt" 2>&1
    echo "alternation $i $side done: $(uptime)"
  done
  i=$((i + 1))
done
