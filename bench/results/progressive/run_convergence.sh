#!/bin/sh
# The convergence measurement of issue 24 (docs/RENDER.md, "Progressive photon mapping"):
# a path-traced reference per scene, then 16 progressive passes of 250k photons per method,
# each pass's running image compared with the reference on 32-px blocks (emitter blocks left out).
# Usage: [SPP=1 GATHER=32] run_convergence.sh BHCL SCENE METHOD [REF.exr]   (in bench/results/progressive)
# SPP camera samples a pixel and GATHER gather rays a sample, each pass (the files get _sppN when SPP > 1).
# The reference (default /tmp/ppm_ref_SCENE.exr) is made when missing: 2048 paths a pixel, and on
# the specular scene the tile (96, 128) again at 131072 (--window, --base): its light is the top of
# the glass block seen in the mirror, lit only through the glass, which the path tracer reaches only
# when a bounce happens to hit the light through the glass; at 2048 paths that tile is ~9 % off
# (256 paths: 39 %), every other tile within ~1.5 %.
set -e
BHCL=$1; SCENE=$2; METHOD=$3; REF=${4:-/tmp/ppm_ref_$SCENE.exr}
SPP=${SPP:-1}; GATHER=${GATHER:-32}; TAG=""; [ "$SPP" -gt 1 ] && TAG=_spp$SPP
NAME=ppm_${SCENE}_$METHOD$TAG
if [ ! -f "$REF" ]; then
  "$BHCL" pathtrace --scene "$SCENE" --size 256x256 --spp 2048 --threads 1 --quiet --out "${REF%.exr}_2048.exr" \
    --stats ref_${SCENE}_256.json
  if [ "$SCENE" = cornell-specular ]; then
    "$BHCL" pathtrace --scene "$SCENE" --size 256x256 --spp 131072 --window 96,128,128,160 \
      --base "${REF%.exr}_2048.exr" --quiet --out "$REF" --stats ref_${SCENE}_256_window.json
  else
    cp "${REF%.exr}_2048.exr" "$REF"
  fi
fi
"$BHCL" render --scene "$SCENE" --size 256x256 --photons 250000 --spp "$SPP" --gather "$GATHER" --passes 16 \
  --method "$METHOD" --reference "$REF" --reference-block 32 --quiet \
  --out /tmp/$NAME.exr --png $NAME.png --stats $NAME.json > $NAME.txt 2>&1
