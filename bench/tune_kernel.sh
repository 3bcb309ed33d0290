#!/usr/bin/env bash
# Measures this device's row of the grid kernel's forms table (lib/src/core/kernel_forms.cpp):
# perf_harness runs the device's current row ("base") beside candidate forms, each one change
# from it (a kernel define, the grid's cell population, the work-group size; three runs at k = 10
# and 50, each with its own base, and a fourth at k = 1 and 8 for the small-k variant's prefetch),
# in interleaved rounds in one process, on each data set and order; tune_pick.py takes the
# median over rows of each candidate's speed against base (same queries, exact, so the rows
# are the same) and prints the winning row in the table's format, with the figures to quote.
#   bench/tune_kernel.sh [build-dir] [data-dir] [rounds]     (POCL_MAX_PTHREAD_COUNT as you run)
set -euo pipefail
cd "$(dirname "$0")/.."
build=${1:-build}
data=${2:-../shared/data}
rounds=${3:-5}
harness=$build/bench/perf_harness
[ -x "$harness" ] || { echo "tune_kernel: $harness not built" >&2; exit 1; }
out=${TUNE_OUT:-bench/results/harness/tune_$(date +%Y%m%d)}
mkdir -p "$(dirname "$out")"
# Candidates: one change each from the device's row (the defines the table's fields set).
cands="base:;fill1:-DBHCL_GRID_FILLSORT=1;fill0:-DBHCL_GRID_FILLSORT=0;rowcap0:-DBHCL_GRID_ROWCAP=0;"
cands+="rowcap8:-DBHCL_GRID_ROWCAP=8;lines1:-DBHCL_GRID_PREFETCH_LINES=1;lines4:-DBHCL_GRID_PREFETCH_LINES=4;"
cands+="pf0:-DBHCL_GRID_PREFETCH=0;walk0:-DBHCL_GRID_WALKCAP=0"
sets=${TUNE_SETS:-uniform,cornell,autzen}
at=(--data "$sets" --data-dir "$data" --N "${TUNE_N:-1000000}" --queries "${TUNE_Q:-100000}"
    --order sorted,random --A 1000000 --rounds "$rounds")
common=("${at[@]}" --k 10,50)
rm -f "$out.csv" "$out.cells.csv" "$out.local.csv" "$out.smallk.csv"
# 1. The kernel's fields (defines).
"$harness" "${common[@]}" --defines "$cands" --csv "$out.csv" | tee "$out.txt"
# 2. The cell population the grid aims at (the build's target_cell_points; base: the row's).
"$harness" "${common[@]}" --bh-build "base:preset=auto;cells16:target_cell_points=16;cells32:target_cell_points=32;cells48:target_cell_points=48" \
  --csv "$out.cells.csv" | tee -a "$out.txt"
# 3. The work-group size (0: the row's).
"$harness" "${common[@]}" --local-size 0,16,32,128 --csv "$out.local.csv" | tee -a "$out.txt"
/usr/bin/env python3 bench/tune_pick.py "$out.csv" "$out.cells.csv" "$out.local.csv" | tee -a "$out.txt"
# 4. Small k (the BHCL_KMAX 8 variant): the 9 rows' prefetch against the home cell's alone
#    (the row's prefetch_ring_from: 16 where ring0 wins here, 0 where ring1 does).
"$harness" "${at[@]}" --k 1,8 --defines "base:;ring0:-DBHCL_GRID_PREFETCH_RING=0;ring1:-DBHCL_GRID_PREFETCH_RING=1" \
  --csv "$out.smallk.csv" | tee -a "$out.txt"
/usr/bin/env python3 bench/tune_pick.py "$out.smallk.csv" | tee -a "$out.txt"
