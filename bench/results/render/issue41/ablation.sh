#!/bin/sh
# Issue 41: which of the talk's rules matters on the diffuse Cornell box (200k photons, k = 50,
# A = 16 and 4, B from the talk's rule for that A): P = ln N against larger P, and the paper
# preset's switches one at a time. Prints one line per run: the options, the relative RMSE
# against the kd-tree render and the lists' false negatives / mean dilation.
# Usage: bench/results/render/issue41/ablation.sh OUTDIR   (from the repository root; ~2 min)
set -eu
out=${1:?usage: ablation.sh OUTDIR}
mkdir -p "$out"
export POCL_MAX_PTHREAD_COUNT=2
i=0
for A in 16 4; do
  for opts in "" "--P 18" "--P 24" "--P 32" "--P 40" "--P 48" "--P 64 --direct-addressing 0" \
              "--keep-top-count 1" "--guard-thresholds 1" "--box-skip 1" "--P 40 --keep-top-count 1"; do
    i=$((i + 1))
    # shellcheck disable=SC2086
    build/host/bhcl render --compare --preset paper --compare-A "$A" --size 160x160 --photons 200000 \
      --gather 16 --seed 1 --quiet $opts --out "$out/abl$i.exr" --stats "$out/abl$i.json" 2> "$out/abl$i.txt"
    /usr/bin/python3 - "$out/abl$i.json" "A=$A $opts" <<'PY'
import json, sys
j = json.load(open(sys.argv[1]))
r = j["runs"][1]
a, b = r["lists_accuracy"], r["build"]
print(f"{sys.argv[2]:<36} P {b['P']:>3} B {b['B']:>2} median cell {b['median_cell_points']:>4.0f}  "
      f"rel. RMSE {100 * r['relative_rmse']:6.2f} %  FN {a['false_negative_rate']:.3f}  "
      f"dil. max {a['max_dilation']:7.2f} mean {a['mean_dilation']:.3f}")
PY
  done
done
