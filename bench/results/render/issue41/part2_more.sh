#!/bin/sh
# Issue 41, part 2, after part2.sh: the longer runs the goal needs, with part2.sh's settings and
# output format: the path tracer at 4096 paths, and 64
# passes of progressive photon mapping with block hashing on the specular scene (its stats'
# pass_reports give the curve for passes 1 .. 64).
# Usage: bench/results/render/issue41/part2_more.sh OUTDIR   (from the repository root)
set -eu
out=${1:?usage: part2_more.sh OUTDIR}
. "$(dirname "$0")/part2_common.sh"
for run in cornell-specular:4096 cornell:4096; do
  pathtrace_point "${run%%:*}" "${run##*:}" "$out/ref_${run%%:*}.exr"
done
ppm_point cornell-specular blockhash 64 "$out/ref_cornell-specular.exr"
