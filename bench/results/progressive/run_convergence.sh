#!/bin/sh
# The convergence measurement of issue 24 (docs/RENDER.md, "Progressive photon mapping"):
# a path-traced reference per scene, then 16 progressive passes of 250k photons per method,
# each pass's running image compared with the reference on 32-px blocks (emitter blocks left out).
# Usage: run_convergence.sh BHCL SCENE METHOD   (the reference /tmp/wt24_ref_SCENE.exr first:
#   BHCL pathtrace --scene SCENE --size 256x256 --spp 2048 --threads 1 --quiet --out /tmp/wt24_ref_SCENE.exr)
set -e
BHCL=$1; SCENE=$2; METHOD=$3
"$BHCL" render --scene "$SCENE" --size 256x256 --photons 250000 --gather 32 --passes 16 --method "$METHOD" \
  --reference /tmp/wt24_ref_$SCENE.exr --reference-block 32 --quiet \
  --out /tmp/wt24_ppm_${SCENE}_$METHOD.exr --png ppm_${SCENE}_$METHOD.png --stats ppm_${SCENE}_$METHOD.json \
  > ppm_${SCENE}_$METHOD.txt 2>&1
