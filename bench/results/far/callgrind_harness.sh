#!/bin/bash
# From the repository root, after a Release build: EXTRA="-D..." PRE="-Idir-with-a-modified-grid_search.h" bash bench/results/far/callgrind_harness.sh TAG
# prints, for k = 1, 10, 50 on two clusters (2000 queries), the cell side and the instructions of the host reference (the kernel's traversal).
# The reference compiled as the library is (-ffp-contract=off: the sums as written, no FMAs; without it, before session 11's
# end, clang contracted them): on d286ea0 k = 1 / 10 / 50 read 12,225,264 / 36,110,112 / 131,629,495, where the same code with
# contraction read 12,279,052 / 36,291,545 / 131,446,268 (walk_h42.txt's last row).
L=${L:-$PWD}; INC="$PRE -I$L/lib/src -I$L/lib/include -I$L/kernels -I$L/build/lib -I$L/build/lib/include"
clang++-15 -std=c++17 -O2 -march=haswell -ffp-contract=off -gdwarf-4 $EXTRA $INC bench/results/far/callgrind_harness.cpp $L/lib/src/blockhash/grid_query_ref.cpp -o /tmp/cg_h_$1 $L/build/lib/libblockhash_cl.a -lOpenCL -lpthread || exit 1
for k in 1 10 50; do echo -n "k$k $(/tmp/cg_h_$1 $k 2000 | awk '{print $8}') "; valgrind --tool=callgrind --toggle-collect='run_query*' --callgrind-out-file=/dev/null /tmp/cg_h_$1 $k 2000 2>&1 | grep Collected | awk '{print $4}'; done
