#!/bin/sh
# bhcl knn --distributed under mpirun writes the same files as bhcl knn in one process, byte for
# byte, for the exact methods (a flat point set, k 20, a radius that cuts rows short), and for
# radius search (--radius, capped); with --id-base 2^32, int64 ids that are the one-process ids
# plus the base; a missing
# input file fails every rank with one message naming it.
# Usage: distributed_cli.sh BHCL MPIEXEC NP WORKDIR [mpiexec options...]
set -eu
bhcl=$1 mpiexec=$2 np=$3 dir=$4
shift 4
mkdir -p "$dir"
cd "$dir"
awk 'BEGIN { srand(7); for (i = 0; i < 20000; i++) printf "%.6f %.6f %.6f\n", rand(), rand(), 0.01 * rand() }' > p.txt
awk 'BEGIN { srand(8); for (i = 0; i < 3000; i++) printf "%.6f %.6f %.6f\n", rand(), rand(), 0.01 * rand() }' > q.txt
for m in kdtree bruteforce; do
  args="--points p.txt --queries q.txt --method $m --k 20 --max-radius 0.01 --quiet"
  "$bhcl" knn $args --out-ids i1 --out-dist2 d1 --out-counts c1
  "$mpiexec" -np "$np" "$@" "$bhcl" knn $args --out-ids iN --out-dist2 dN --out-counts cN --distributed
  cmp i1 iN && cmp d1 dN && cmp c1 cN
  echo "$m: $np rank(s) wrote the one-process files"
done
# Issue 22: rank 0 writes the rows in slices as they come back (here 5 slices of 700 queries, every
# rank taking part in each call): the same files.
args="--points p.txt --queries q.txt --method kdtree --k 20 --max-radius 0.01 --quiet"
BHCL_SLICE_ROWS=700 "$mpiexec" -np "$np" "$@" "$bhcl" knn $args --out-ids iS --out-dist2 dS --out-counts cS --distributed
"$bhcl" knn $args --out-ids i1 --out-dist2 d1 --out-counts c1
cmp i1 iS && cmp d1 dS && cmp c1 cS
echo "kdtree in slices: $np rank(s) wrote the one-process files"
# Direct outputs with the taper (3000 queries: 4 slices of 700, a last of 200): only rank 0 writes, so only its
# slicing has the taper; every rank must take rank 0's (else the ranks' calls part and it hangs).
BHCL_DIRECT_OUTPUT=1 BHCL_SLICE_ROWS=700 BHCL_LAST_SLICE_ROWS=200 "$mpiexec" -np "$np" "$@" "$bhcl" knn $args \
  --out-ids iT --out-dist2 dT --out-counts cT --distributed
cmp i1 iT && cmp d1 dT && cmp c1 cT
echo "kdtree in tapered direct slices: $np rank(s) wrote the one-process files"
# Issue 25: an id base of 2^32: the ids are written as int64, each the one-process id plus the
# base (-1 stays -1); distances as one process's; NPY gets '<i8'.
"$mpiexec" -np "$np" "$@" "$bhcl" knn $args --out-ids iB --out-dist2 dB --distributed --id-base 4294967296
cmp d1 dB
od -An -v -t d4 i1 | tr -s ' ' '\n' | sed '/^$/d' | awk '{ printf "%.0f\n", $1 < 0 ? -1 : $1 + 4294967296 }' > want.txt
od -An -v -t d8 iB | tr -s ' ' '\n' | sed '/^$/d' | awk '{ printf "%.0f\n", $1 }' > got.txt
cmp want.txt got.txt
"$mpiexec" -np "$np" "$@" "$bhcl" knn $args --out-ids iB.npy --out-dist2 dB.npy --distributed --id-base 4294967296
head -c 128 iB.npy | grep -q "'descr': '<i8'"
echo "id base 2^32: $np rank(s) wrote int64 ids, the one-process ids plus the base"
# Radius search: the same three arrays as one process (an exact method, a cap).
rargs="--points p.txt --queries q.txt --method kdtree --radius 0.02 --max-results 30 --quiet"
"$bhcl" knn $rargs --out-offsets o1 --out-ids ri1 --out-dist2 rd1
"$mpiexec" -np "$np" "$@" "$bhcl" knn $rargs --out-offsets oN --out-ids riN --out-dist2 rdN --distributed
cmp o1 oN && cmp ri1 riN && cmp rd1 rdN
echo "radius: $np rank(s) wrote the one-process files"
BHCL_SLICE_ROWS=700 "$mpiexec" -np "$np" "$@" "$bhcl" knn $rargs --out-offsets oS --out-ids riS --out-dist2 rdS --distributed
cmp o1 oS && cmp ri1 riS && cmp rd1 rdS
echo "radius in slices: $np rank(s) wrote the one-process files"
if "$mpiexec" -np "$np" "$@" "$bhcl" knn --points missing.txt --queries q.txt --method kdtree \
    --out-ids iN --out-dist2 dN --distributed --quiet 2> err.txt; then
  echo "a missing point file did not fail"; exit 1
fi
lines=$(grep -c "rank 0: missing.txt" err.txt || true)
if [ "$lines" -ne "$np" ]; then
  echo "expected the error on each of $np ranks, got $lines:"; cat err.txt; exit 1
fi
echo "a missing file failed all $np ranks"
