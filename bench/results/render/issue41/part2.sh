#!/bin/sh
# Issue 41, part 2: error against wall time, progressive photon mapping (block hashing's default
# and the kd-tree) against the path tracer, both Cornell boxes, 128x128 (reduced from the issue's
# 256x256: 2 shared cores). Errors against a 2048-path reference: the worst 16x16 tile and the
# RMSE over the tiles (emitter tiles left out), and on the specular scene the caustic region
# (the floor under the glass, 0.50,0.89,0.72,0.925 of the image; docs/RENDER.md, issue 12).
# Usage: bench/results/render/issue41/part2.sh OUTDIR   (from the repository root; ~10 min)
# Needs image_errors (g++ -O2 -std=c++17 image_errors.cpp $(pkg-config --cflags --libs OpenEXR)
# -o OUTDIR/image_errors). Prints one line per image: scene method samples seconds tile_rmse worst region.
set -eu
out=${1:?usage: part2.sh OUTDIR}
. "$(dirname "$0")/part2_common.sh"
for scene in cornell-specular cornell; do
  ref="$out/ref_$scene.exr"
  if [ ! -f "$ref" ]; then
    $B pathtrace --scene "$scene" --size $SIZE --spp 2048 --threads 2 --quiet --out "$ref" --stats "$out/ref_$scene.json"
    if [ "$scene" = cornell-specular ]; then
      # The tiles 2048 paths leave a few per cent off, traced again into the same image: the floor
      # under the glass (65536 paths), the glass top seen in the mirror and the floor by the
      # mirror's foot (131072; both renders of the first pass were 3-4 % below 2048 paths there).
      for w in 64,112,96,120:65536 48,64,64,80:131072 48,96,64,112:131072; do
        mv "$ref" "$out/ref_base.exr"
        $B pathtrace --scene "$scene" --size $SIZE --spp "${w##*:}" --threads 2 --window "${w%%:*}" \
          --base "$out/ref_base.exr" --quiet --out "$ref"
      done
      rm -f "$out/ref_base.exr"
    fi
  fi
  for spp in 4 16 64 256 1024; do
    pathtrace_point "$scene" $spp "$ref"
  done
  for method in blockhash kdtree; do
    for passes in 1 4 16; do
      [ "$scene" = cornell ] && [ "$passes" != 16 ] && continue
      ppm_point "$scene" $method $passes "$ref"
    done
  done
done
