#!/bin/sh
# Issue 41: the talk's sheet (kd-tree, block hashing at A = 4, 8, 16) for the diffuse and the
# specular Cornell box at 200k and 1M photons, with the paper preset and with paper-cells.
# Usage: bench/results/render/issue41/run.sh OUTDIR   (from the repository root; ~2 min on 2 cores)
# Writes OUTDIR/<scene>_<photons>_<preset>{.json,_compare.png,...}; make_sheet.py assembles the
# committed sheets from the _compare.png files.
set -eu
out=${1:?usage: run.sh OUTDIR}
mkdir -p "$out"
export POCL_MAX_PTHREAD_COUNT=2
for scene in cornell specular; do
  arg=cornell
  [ "$scene" = specular ] && arg=host/scenes/cornell-specular.obj
  for photons in 200000 1000000; do
    for preset in paper paper-cells; do
      name="$out/${scene}_${photons}_${preset}"
      build/host/bhcl render --compare --scene "$arg" --preset "$preset" --compare-A 4,8,16 \
        --size 160x160 --photons "$photons" --gather 16 --seed 1 --quiet \
        --out "$name.exr" --stats "$name.json" 2> "$name.txt"
    done
  done
done
