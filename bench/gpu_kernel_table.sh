#!/usr/bin/env bash
# The sm_90 (H100/H200) table of every OpenCL kernel the library builds, without a GPU:
# registers, per-thread stack frame and spills from `ptxas -v`.
#
# Usage: bash bench/gpu_kernel_table.sh [BUILD_DIR] [kernel_dump options, e.g. --N 100000]
#
# 1. BUILD_DIR/bench/kernel_dump builds every method's programs (every k variant, kNN and radius)
#    with BHCL_DUMP_PROGRAMS=dir, so the library writes each program's source (includes resolved)
#    and its full build options; BHCL_QUIRKS_AS=nvidia and BHCL_KERNEL_FORM=gpu-nvidia make the
#    defines those of an NVIDIA GPU (the quirks and the grid kernel's row of the forms table).
# 2. Each program goes through clang-15's OpenCL front end for nvptx64 with libclc's builtins
#    (Debian libclc-15: /usr/lib/clc/nvptx64--nvidiacl.bc) to PTX (LLVM 15 targets up to sm_86;
#    PTX is forward compatible), then `ptxas -v -arch=sm_90`.
# Prints one row per kernel and k variant; exits 1 when a program no longer compiles. Where
# ptxas, clang-15, libclc or kernel_dump is missing it says so and exits 0 (a skip).
# Tools: PTXAS, CLANG, LIBCLC override the paths; JOBS the parallel compiles (default: nproc).
set -euo pipefail
cd "$(dirname "$0")/.."
build=${1:-build}
shift || true
ptxas=${PTXAS:-$(command -v ptxas || echo /usr/local/cuda/bin/ptxas)}
clang=${CLANG:-$(command -v clang-15 || echo /usr/lib/llvm-15/bin/clang)}
libclc=${LIBCLC:-/usr/lib/clc/nvptx64--nvidiacl.bc}
dump_tool=$build/bench/kernel_dump
skip() { echo "gpu_kernel_table: skipped: $1"; exit 0; }
[ -x "$ptxas" ] || skip "ptxas not found (CUDA toolkit; set PTXAS)"
[ -x "$clang" ] || skip "clang-15 not found (set CLANG)"
[ -f "$libclc" ] || skip "$libclc not found (Debian: apt-get install libclc-15; set LIBCLC)"
[ -f /usr/include/clc/clc.h ] || skip "/usr/include/clc/clc.h not found (libclc-15-dev)"
[ -x "$dump_tool" ] || skip "$dump_tool not built (bench/ needs FLANN)"

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/dump"
# Enough points that the data-dependent defines are those of a 1M-point index (kd-tree stack,
# paper's L); the builds take seconds.
BHCL_DUMP_PROGRAMS="$work/dump" BHCL_QUIRKS_AS=nvidia BHCL_KERNEL_FORM=gpu-nvidia "$dump_tool" "$@" > "$work/dump.log" 2>&1 || {
  cat "$work/dump.log"
  echo "gpu_kernel_table: kernel_dump failed"
  exit 1
}

# $1 = dump/NAME.cl: writes NAME.ptx and NAME.ptxas (ptxas -v); NAME.err stays only on failure.
compile_one() {
  local cl=$1 base=${1%.cl}
  local opts
  opts=$(cat "$base.options")
  # shellcheck disable=SC2086  # the options are words
  if ! "$clang" -x cl $opts -target nvptx64--nvidiacl -I/usr/include -include clc/clc.h \
      -Dcl_clang_storage_class_specifiers -O3 -Xclang -mlink-builtin-bitcode -Xclang "$libclc" \
      -Xclang -target-cpu -Xclang sm_86 -S -o "$base.ptx" "$cl" > "$base.err" 2>&1; then
    return 0
  fi
  if ! "$ptxas" -v -arch=sm_90 "$base.ptx" -o "$base.cubin" > "$base.ptxas" 2>&1; then
    cat "$base.ptxas" >> "$base.err"
    return 0
  fi
  rm -f "$base.err"
}
export -f compile_one
export clang ptxas libclc
find "$work/dump" -name '*.cl' -print0 |
  xargs -0 -n 1 -P "${JOBS:-$(nproc)}" bash -c 'compile_one "$0"'

failed=0
for err in "$work"/dump/*.err; do
  [ -e "$err" ] || continue
  failed=1
  echo "gpu_kernel_table: FAILED: $(basename "${err%.err}").cl with options: $(cat "${err%.err}.options")"
  head -n 30 "$err"
done

# One row per entry function: kernel, the program's BHCL_KMAX (- when it has none), registers,
# stack frame bytes, spill stores and loads.
{
  for log in "$work"/dump/*.ptxas; do
    [ -e "$log" ] || continue
    opts=$(cat "${log%.ptxas}.options")
    kmax=$(sed -n 's/.*-DBHCL_KMAX=\([0-9]*\).*/\1/p' <<< "$opts")
    awk -v kmax="${kmax:--}" '
      /Compiling entry function/ { match($0, /'"'"'[^'"'"']*'"'"'/); name = substr($0, RSTART + 1, RLENGTH - 2); entry = 1 }
      /Function properties for/ { props = $NF }
      entry && props == name && /bytes stack frame/ { stack = $1; st = $5; ld = $9 }
      entry && /Used [0-9]+ registers/ { for (i = 1; i <= NF; ++i) if ($i == "Used") regs = $(i + 1);
        printf "%s %s %s %s %s %s\n", name, kmax, regs, stack, st, ld; entry = 0 }
    ' "$log"
  done
} | sort -k1,1 -k2,2n > "$work/rows"
printf '%-26s %5s %5s %8s %12s %11s\n' kernel kmax regs "stack B" "spill st B" "spill ld B"
while read -r name kmax regs stack st ld; do
  printf '%-26s %5s %5s %8s %12s %11s\n' "$name" "$kmax" "$regs" "$stack" "$st" "$ld"
done < "$work/rows"
grep -h "kernel variants built" "$work/dump.log" | sed 's/^/# /' || true
if [ "$failed" -ne 0 ]; then
  echo "gpu_kernel_table: some kernels did not compile for sm_90"
  exit 1
fi
