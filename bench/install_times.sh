#!/usr/bin/env bash
# Times `pip install .` the way README and docs/PYTHON.md tell users (issue 40, part 4): a fresh
# clone of REPO in a temporary directory, a virtual environment over Debian's python3
# (--system-site-packages: its numpy), then a first install (empty build dir), a second (nothing
# changed) and a third after touching one library source. ccache is off (CCACHE_DISABLE=1, no
# compiler launcher), so every object not recompiled was kept by scikit-build-core's build dir
# (pyproject.toml: build-dir), not fetched from a cache. Per install: the wall time, the load
# average, which pybind11 the bindings used, and the objects Ninja compiled.
# Usage: bash bench/install_times.sh [REPO (default: this checkout)] [PYTHON (default /usr/bin/python3)]
#        > bench/results/python/install_times.txt
# KEEP=1 keeps the clone and its venv (its path printed at the end); otherwise removed at exit.
set -uo pipefail
src=$(cd "${1:-$(dirname "$0")/..}" && pwd)
py=${2:-/usr/bin/python3}
export CCACHE_DISABLE=1
unset CMAKE_CXX_COMPILER_LAUNCHER CMAKE_C_COMPILER_LAUNCHER
work=$(mktemp -d /tmp/bhcl-install-times.XXXXXX)
[ "${KEEP:-0}" = 1 ] || trap 'rm -rf "$work"' EXIT
git clone -q "$src" "$work/clone" || { echo "install_times: cannot clone $src" >&2; exit 1; }
cd "$work/clone"
echo "# fresh clone of $src at $(git rev-parse --short HEAD): $(git log -1 --format=%s | cut -c1-90)"
echo "# $(date -u +%FT%TZ); $(nproc) cores ($(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'), shared with other work); CCACHE_DISABLE=1, no compiler launcher"
"$py" -m venv --system-site-packages .venv
echo "# $(.venv/bin/python --version); $(.venv/bin/python -m pip --version | cut -d' ' -f1-2); command: .venv/bin/python -m pip install -v ."

one() {  # label, log name, how many compiled objects to list
  local label=$1 log=$work/pip_$2.log show=$3
  echo
  echo "## $label"
  echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg)"
  local t0 t1 rc
  t0=$(date +%s.%N)
  .venv/bin/python -m pip install -v . > "$log" 2>&1
  rc=$?
  t1=$(date +%s.%N)
  echo "rc $rc, wall $(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.1f", b - a }') s; load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
  [ $rc -eq 0 ] || { tail -30 "$log"; exit 1; }
  grep -m1 -E "scikit-build-core [0-9]" "$log" | sed 's/^ *//'
  grep -m1 -E "pybind11 [0-9.]+ from" "$log" | sed 's/^ *-- /  /'
  local steps cxx lib
  steps=$(grep -cE '^ *\[[0-9]+/[0-9]+\]' "$log")
  cxx=$(grep -cE 'Building CXX object' "$log")
  lib=$(grep -E 'Building CXX object' "$log" | grep -c 'lib/CMakeFiles/')
  echo "ninja steps run: $steps; C++ objects compiled: $cxx (of them in lib/CMakeFiles: $lib)"
  echo "build step (pip -v):"
  sed -n '/Configuring CMake/,/Created blockhash_cl/p' "$log" |
    grep -E 'Configuring CMake|initial cache|CXX compiler identification|Building project|ninja: no work|^ *\[[0-9]+/[0-9]+\]|Created blockhash_cl' |
    sed -E 's/^ */  /' | awk -v n="$show" '/\[[0-9]+\/[0-9]+\]/ { if (++c > n) { skipped++; next } } { print } END { if (skipped) print "  ... (" skipped " more ninja steps)" }'
}

one "1. first install (fresh clone, empty build dir)" 1 4
one "2. second install, nothing changed" 2 20
touch lib/src/core/metrics.cpp
one "3. third install, after touch lib/src/core/metrics.cpp" 3 20
echo
echo "## what the build dir kept"
for d in build/python/*/; do
  echo "$d: $(find "$d" -path '*lib/CMakeFiles/*' -name '*.o' | wc -l) library objects under lib/CMakeFiles, CMakeCache.txt $( [ -f "$d/CMakeCache.txt" ] && echo present || echo absent)"
done
echo
echo "## versions"
(cd / && "$work/clone/.venv/bin/python" -c "import blockhash_cl as b; from importlib import metadata; print('blockhash_cl.__version__', b.__version__, '| distribution metadata', metadata.version('blockhash_cl'))")
[ -x "$src/build/host/bhcl" ] && echo "$("$src/build/host/bhcl" --version) ($src/build/host/bhcl)"
echo "CHANGELOG.md's latest release: $(grep -m1 -E '^## \[[0-9]' CHANGELOG.md)"
[ "${KEEP:-0}" = 1 ] && echo "# kept: $work (clone and .venv)"
exit 0
