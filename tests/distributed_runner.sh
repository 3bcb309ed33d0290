#!/bin/sh
# bhcl knn's one runner (issue 35): at 2 ranks, bhcl knn --distributed writes the files bhcl knn
# writes on one device (and --device pocl,pocl), byte for byte, for block hashing's default (the
# exact grid) in kNN and radius search; the three stats files carry the same fields, each kind
# adding only its own ("devices", "distributed") and the one-device run its index's memory.
# Usage: distributed_runner.sh BHCL MPIEXEC WORKDIR [mpiexec options...]
set -eu
bhcl=$1 mpiexec=$2 dir=$3
shift 3
mkdir -p "$dir"
cd "$dir"
awk 'BEGIN { srand(11); for (i = 0; i < 20000; i++) printf "%.6f %.6f %.6f\n", rand(), rand(), rand() }' > p.txt
awk 'BEGIN { srand(12); for (i = 0; i < 3000; i++) printf "%.6f %.6f %.6f\n", rand(), rand(), rand() }' > q.txt
# keys FILE: the stats file's top-level fields, one a line, sorted.
keys() { python3 -c 'import json, sys; print("\n".join(sorted(json.load(open(sys.argv[1])))))' "$1"; }
for mode in knn radius; do
  if [ "$mode" = knn ]; then
    args="--points p.txt --queries q.txt --method blockhash --k 12 --quiet"
    files() { echo "--out-ids i$1 --out-dist2 d$1 --out-counts c$1 --stats s$1.json"; }
  else
    args="--points p.txt --queries q.txt --method blockhash --radius 0.04 --quiet"
    files() { echo "--out-offsets o$1 --out-ids i$1 --out-dist2 d$1 --out-counts c$1 --stats s$1.json"; }
  fi
  "$bhcl" knn $args $(files 1)
  "$bhcl" knn $args $(files M) --device pocl,pocl
  "$mpiexec" -np 2 "$@" "$bhcl" knn $args $(files D) --distributed
  for f in i d c; do cmp ${f}1 ${f}D; cmp ${f}1 ${f}M; done
  if [ "$mode" = radius ]; then cmp o1 oD; cmp o1 oM; fi
  keys s1.json | grep -v '^memory_bytes$' > k1
  keys sD.json | grep -v '^distributed$' > kD
  keys sM.json | grep -v '^devices$' > kM
  cmp k1 kD || { diff k1 kD; exit 1; }
  # The several-device index has no one index to report the build and search parameters of.
  grep -v -e '^build$' -e '^search$' k1 > k1M
  cmp k1M kM || { diff k1M kM; exit 1; }
  echo "$mode: 2 ranks and 2 devices wrote the one-device files; the stats carry the same fields"
done
