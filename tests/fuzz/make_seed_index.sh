#!/usr/bin/env bash
# Regenerates the seed indexes of fuzz_index_load (small block-hash indexes saved by bhcl, one
# per L-table preset: auto's with grid 0, and paper's) and fuzz_grid_load (the default grid
# layout).
# Usage: tests/fuzz/make_seed_index.sh BUILD_DIR
set -euo pipefail
build=${1:-build}
dir=$(dirname "$0")/seeds/fuzz_index_load
grid_dir=$(dirname "$0")/seeds/fuzz_grid_load
mkdir -p "$dir" "$grid_dir"
python3 -c "
import random, struct
random.seed(1)
open('/tmp/bhcl_seed_points.f32','wb').write(b''.join(struct.pack('<3f', random.random(), random.random(), random.random()) for _ in range(300)))"
"$build/host/bhcl" knn --points /tmp/bhcl_seed_points.f32 --queries /tmp/bhcl_seed_points.f32 --k 4 \
  --method blockhash --grid 0 --save-index "$dir/small_auto.bhidx" --out-ids /dev/null --out-dist2 /dev/null
"$build/host/bhcl" knn --points /tmp/bhcl_seed_points.f32 --queries /tmp/bhcl_seed_points.f32 --k 4 \
  --method blockhash --preset paper --save-index "$dir/small_paper.bhidx" --out-ids /dev/null --out-dist2 /dev/null
for d in 0 1; do  # the direct and the two-level cell directory
  "$build/host/bhcl" knn --points /tmp/bhcl_seed_points.f32 --queries /tmp/bhcl_seed_points.f32 --k 4 \
    --method blockhash --grid-directory $d --save-index "$grid_dir/small_grid_dir$d.bhgrid" --out-ids /dev/null --out-dist2 /dev/null
done
rm -f /tmp/bhcl_seed_points.f32
ls -la "$dir" "$grid_dir"
