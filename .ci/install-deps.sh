#!/usr/bin/env bash
# Installs the Debian 12 packages blockhash_cl builds and runs with, skipping those already there.
# Usage: bash .ci/install-deps.sh [--ci]   (as root, or a user with sudo)
#   --ci adds what CI's sanitizer and fuzzing runs need (clang and its runtimes).
set -euo pipefail

packages=(
  build-essential cmake ninja-build pkg-config
  ocl-icd-opencl-dev opencl-c-headers opencl-clhpp-headers pocl-opencl-icd clinfo
  libembree-dev libopenexr-dev libpng-dev libfreetype-dev fonts-dejavu-core
  libflann-dev liblz4-dev libnanoflann-dev
  doctest-dev libcli11-dev nlohmann-json3-dev
  libopenmpi-dev openmpi-bin
  python3 python3-numpy python3-matplotlib
  python3-venv python3-dev pybind11-dev python3-scipy python3-pytest
  python3-mpi4py  # the Python DistributedIndex's tests under mpirun (the package itself works without it)
  locales  # localedef: the locale tests build de_DE.UTF-8 in a private LOCPATH (no root)
)
if [ "${1:-}" = "--ci" ]; then
  # libclc-15: libclc's nvptx builtins for bench/gpu_kernel_table.sh (with the CUDA toolkit's
  # ptxas where installed; the step skips without it). ccache: .ci/run's compiler cache, kept
  # between runs (~/.cache/blockhash_cl-ci unless BHCL_CI_CACHE names another place).
  packages+=(clang libclang-rt-14-dev libclc-15 ccache)
fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all ${#packages[@]} packages already installed"
  exit 0
fi

echo "install-deps: installing ${missing[*]}"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
