# Sourced by part2.sh and part2_more.sh (after they set $out): the settings both run with and the
# runs both make, so that every line of points.txt is made and measured the same way.
export POCL_MAX_PTHREAD_COUNT=2
B=build/host/bhcl
SIZE=128x128
REGION=0.50,0.89,0.72,0.925

# The wall time of a run, from its stats JSON (total_s).
seconds() { /usr/bin/python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['total_s'])" "$1"; }

# Usage: point SCENE METHOD SAMPLES NAME REF. One line of points.txt for NAME.exr (stats in
# NAME.json) against the reference REF: scene method samples seconds tile_rmse worst region.
point() {
  echo "$1 $2 $3 $(seconds "$4.json") $("$out/image_errors" "$4.exr" "$5" 16 $REGION)"
}

# Usage: pathtrace_point SCENE SPP REF. The path tracer at SPP paths a pixel (seed 7), its line.
pathtrace_point() {
  name="$out/pt_${1}_${2}"
  $B pathtrace --scene "$1" --size $SIZE --spp "$2" --threads 2 --seed 7 --quiet --out "$name.exr" \
    --stats "$name.json" 2> "$name.txt"
  point "$1" pathtrace "$2" "$name" "$3"
}

# Usage: ppm_point SCENE METHOD PASSES REF. Progressive photon mapping (seed 7) with METHOD's
# index, its line; per pass against REF (the stats' pass_reports) only in a progressive render.
ppm_point() {
  name="$out/ppm_${1}_${2}_${3}"
  refopt=""
  [ "$3" -gt 1 ] && refopt="--reference $4 --reference-block 16"
  # shellcheck disable=SC2086
  $B render --scene "$1" --size $SIZE --spp 4 --gather 8 --photons 250000 --passes "$3" --seed 7 \
    --method "$2" $refopt --quiet --out "$name.exr" --stats "$name.json" 2> "$name.txt"
  point "$1" "ppm-$2" "$3" "$name" "$4"
}
