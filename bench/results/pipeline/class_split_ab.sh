#!/bin/sh
# Each block-hashing algorithm its own class (issue 35): main's perf_harness (BEFORE_DIR) against
# this branch's (build/bench), in alternation (bench/call_ab.py: the median of per-round ratios
# before/after of 1/qps; > 1 means the branch is faster), AVX-512, 2 threads.
set -e
B=${BEFORE_DIR:-/tmp/h35c_before}
OUT=bench/results/pipeline
export POCL_MAX_PTHREAD_COUNT=2
python3 bench/call_ab.py --before $B/perf_harness --after build/bench/perf_harness --alternations ${ALTERNATIONS:-2} \
  --out $OUT/class_split_rounds -- --data cornell,uniform,autzen --queries 100000 --k 10,50 --order random,sorted --rounds 3 \
  > $OUT/class_split_ab.txt
