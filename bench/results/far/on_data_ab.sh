#!/bin/sh
# Issue 36's "no loss on the data": perf_harness's 12 rows (Cornell, uniform, Autzen 1M; k = 10, 50;
# random and sorted order; exact) of main at the filing (7f729ba, BEFORE_DIR) against
# today's (build/bench), processes alternating (bench/call_ab.py). Summarise load-free with
# `python3 bench/results/pipeline/class_split_vs_kd.py bench/results/far/on_data_rounds`
# (block hashing over the kd-tree kernel in each process, after over before). AVX-512, 2 threads.
set -e
B=${BEFORE_DIR:-/work/base36/build/bench}
OUT=bench/results/far
export POCL_MAX_PTHREAD_COUNT=2
python3 bench/call_ab.py --before $B/perf_harness --after build/bench/perf_harness --alternations ${ALTERNATIONS:-3} \
  --out $OUT/on_data_rounds -- --data cornell,uniform,autzen --queries 100000 --k 10,50 --order random,sorted --A 1000000 --rounds 3 \
  --data-dir "${BHCL_DATA_DIR:-../shared/data}" > $OUT/on_data_ab.txt
