#!/bin/bash
# From the repository root, after a Release build: [PRE="-Idir-with-another-grid_search.h"] bash bench/results/far/on_data_callgrind.sh TAG
# L=/path/to/another/tree (its own Release build; LIB= its libblockhash_cl.a where not build/lib/) EXTRA=-DBHCL_OLD7F: the traversal as it was at 7f729ba (issue 36 filed).
# prints, for sets uniform and walls, k = 1, 10, 50 (2000 queries on the data), the points examined a query and the
# instructions of the host reference (the kernel's traversal; on_data_callgrind.cpp), compiled as callgrind_harness.sh does.
L=${L:-$PWD}; LIB=${LIB:-$L/build/lib/libblockhash_cl.a}; INC="$PRE -I$L/lib/src -I$L/lib/include -I$L/kernels -I$L/build/lib -I$L/build/lib/include -I$L/build -I$L/build/include -I$L/build/generated/include"
clang++-15 -std=c++17 -O2 -march=haswell -ffp-contract=off -gdwarf-4 $EXTRA $INC bench/results/far/on_data_callgrind.cpp $L/lib/src/blockhash/grid_query_ref.cpp -o /tmp/cg_od_$1 $LIB -lOpenCL -lpthread || exit 1
for set in uniform walls; do for k in 1 10 50; do
  echo -n "$set k$k examined $(/tmp/cg_od_$1 $set $k 2000 | awk '{print $13}') instr "
  valgrind --tool=callgrind --toggle-collect='run_query*' --callgrind-out-file=/dev/null /tmp/cg_od_$1 $set $k 2000 2>&1 | grep Collected | awk '{print $4}'
done; done
