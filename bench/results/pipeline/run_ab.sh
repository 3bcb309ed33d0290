#!/bin/sh
# The one query pipeline's before/after (issue 35): main's build (BEFORE_DIR) against this branch's
# (build/bench), in alternation, AVX-512, 2 threads. BEFORE_DIR holds call_bench, perf_harness and
# radius_bench built from main at bcf272a plus the commit that added call_bench (d3d5d80).
set -e
B=${BEFORE_DIR:-/tmp/h35p_before}
OUT=bench/results/pipeline
export POCL_MAX_PTHREAD_COUNT=2
python3 bench/call_ab.py --before $B/call_bench --after build/bench/call_bench --alternations 6 \
  --out $OUT/call_rounds -- --data uniform,cornell --N 200000 --n 1000,20000 --k 1,10 --rounds 3 --reps 5 \
  > $OUT/call_ab.txt
python3 bench/call_ab.py --before $B/perf_harness --after build/bench/perf_harness --alternations 4 \
  --out $OUT/ph_rounds -- --data uniform,cornell --N 200000 --queries 20000 --k 1,10 --rounds 5 --order random --A 8 \
  > $OUT/perf_harness_ab.txt
