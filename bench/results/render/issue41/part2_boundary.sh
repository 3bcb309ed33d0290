#!/bin/sh
# Issue 41, part 2 again with the boundary-corrected density estimate (bhcl render --boundary
# surface, host/render/surface_area.hpp) beside the plain one (--boundary none), the path tracer at
# growing samples in the same session (its wall times then meet the same load), part2.sh's
# settings, references and output format (part2_common.sh). The method column says the
# correction: ppm-blockhash-surface, ppm-blockhash-none, ...
# Usage: bench/results/render/issue41/part2_boundary.sh OUTDIR   (from the repository root)
# OUTDIR must hold image_errors and part2.sh's references ref_cornell-specular.exr and
# ref_cornell.exr (part2.sh OUTDIR makes them first; they are the same images bit for bit).
set -eu
out=${1:?usage: part2_boundary.sh OUTDIR}
. "$(dirname "$0")/part2_common.sh"

# Usage: ppm_boundary_point SCENE METHOD PASSES REF BOUNDARY. As ppm_point, with --boundary.
ppm_boundary_point() {
  name="$out/ppm_${1}_${2}_${3}_$5"
  $B render --scene "$1" --size $SIZE --spp 4 --gather 8 --photons 250000 --passes "$3" --seed 7 \
    --method "$2" --boundary "$5" --reference "$4" --reference-block 16 --quiet --out "$name.exr" \
    --stats "$name.json" 2> "$name.txt"
  point "$1" "ppm-$2-$5" "$3" "$name" "$4"
}

for scene in cornell-specular cornell; do
  ref="$out/ref_$scene.exr"
  for spp in 4 16 64 256 1024 4096; do
    pathtrace_point "$scene" $spp "$ref"
  done
  for passes in 4 16 64; do
    for b in surface none; do
      ppm_boundary_point "$scene" blockhash $passes "$ref" $b
    done
  done
  ppm_boundary_point "$scene" kdtree 16 "$ref" surface
done
# The long runs: does the corrected estimate reach 2 % worst tile, and when does the path tracer.
pathtrace_point cornell-specular 8192 "$out/ref_cornell-specular.exr"
ppm_boundary_point cornell-specular blockhash 256 "$out/ref_cornell-specular.exr" surface
