#!/bin/bash
# After on_data_callgrind.sh TAG has built /tmp/cg_od_TAG (one per tree).
# byfile.sh TAG: per (set, k) the host reference's instructions split by source file: traversal (grid_search.h, bhcl_arith.h, cmath) and the reference's own loop (grid_query_ref.cpp, other)
for set in uniform walls; do for k in 1 10 50; do
  valgrind --tool=callgrind --dump-instr=no --toggle-collect='run_query*' --callgrind-out-file=/tmp/cg_od_$1_$set$k.out /tmp/cg_od_$1 $set $k 2000 > /dev/null 2>&1
  callgrind_annotate /tmp/cg_od_$1_$set$k.out 2>/dev/null | awk -v t=$1 -v s=$set -v k=$k '
    /PROGRAM TOTALS/ {gsub(",","",$1); tot=$1}
    /^ *[0-9,]+ +\(/ && /:/ {n=$1; gsub(",","",n); if ($0 ~ /grid_search.h/) gs+=n; else if ($0 ~ /bhcl_arith.h/) ar+=n; else if ($0 ~ /cmath/) cm+=n; else if ($0 ~ /grid_query_ref.cpp/) rf+=n}
    END {printf "%s %s k%s total %d grid_search.h %d bhcl_arith.h %d cmath %d grid_query_ref.cpp %d\n", t, s, k, tot, gs, ar, cm, rf}'
done; done
