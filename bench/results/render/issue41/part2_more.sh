#!/bin/sh
# Issue 41, part 2, after part2.sh: the longer runs the goal needs, with part2.sh's settings and
# output format: the path tracer at 4096 paths, and 64
# passes of progressive photon mapping with block hashing on the specular scene (its stats'
# pass_reports give the curve for passes 1 .. 64).
# Usage: bench/results/render/issue41/part2_more.sh OUTDIR   (from the repository root)
set -eu
out=${1:?usage: part2_more.sh OUTDIR}
export POCL_MAX_PTHREAD_COUNT=2
B=build/host/bhcl
SIZE=128x128
REGION=0.50,0.89,0.72,0.925
seconds() { /usr/bin/python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['total_s'])" "$1"; }
for run in cornell-specular:4096 cornell:4096; do
  scene=${run%%:*}; spp=${run##*:}
  name="$out/pt_${scene}_$spp"
  $B pathtrace --scene "$scene" --size $SIZE --spp "$spp" --threads 2 --seed 7 --quiet --out "$name.exr" \
    --stats "$name.json" 2> "$name.txt"
  echo "$scene pathtrace $spp $(seconds "$name.json") $("$out/image_errors" "$name.exr" "$out/ref_$scene.exr" 16 $REGION)"
done
scene=cornell-specular
name="$out/ppm_${scene}_blockhash_64"
$B render --scene $scene --size $SIZE --spp 4 --gather 8 --photons 250000 --passes 64 --seed 7 --method blockhash \
  --reference "$out/ref_$scene.exr" --reference-block 16 --quiet --out "$name.exr" --stats "$name.json" 2> "$name.txt"
echo "$scene ppm-blockhash 64 $(seconds "$name.json") $("$out/image_errors" "$name.exr" "$out/ref_$scene.exr" 16 $REGION)"
