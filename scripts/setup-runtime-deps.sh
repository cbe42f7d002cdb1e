#!/usr/bin/env bash
# Installs what the built framediffuser-server, framediffuser-client and
# framediffuser-scenegen need to RUN (no compilers, no -dev packages), from
# Debian 12 packages: the runtime stage of deploy/docker/Dockerfile.cpu.
# Idempotent like scripts/setup-deps.sh; apt pulls each library's own
# dependencies (LibTorch brings many).
#
# Usage: scripts/setup-runtime-deps.sh [--check | --list]
#   --check  report missing packages, exit 1 if any
#   --list   print the package names, one per line, and exit
#
# tests/deploy/runtime_deps_test.sh checks that every name exists in Debian
# and that every shared library the built binaries link directly comes from
# one of these packages, so a new library dependency fails a test here, not
# a container start.
set -euo pipefail

PACKAGES=(
  # model runtime: LibTorch (CPU), the fast BLAS it should use, Sleef (the
  # fused CPU attention kernel links it directly) and GCC's OpenMP runtime
  # (LibTorch's, which the project's own CPU kernels now link too)
  libtorch1.13 libopenblas0-pthread libsleef3 libgomp1
  # wire API and server
  libgrpc++1.51 libgrpc29 libprotobuf32 libabsl20220623 libprometheus-cpp-core1.0
  # compression and image files (client CLI, scene generator)
  libzstd1 libpng16-16 libjpeg62-turbo libopenexr-3-1-30
  # C/C++ runtime (present in every Debian image; listed so the check is complete)
  libc6 libgcc-s1 libstdc++6
)

if [[ "${1:-}" == "--list" ]]; then
  printf '%s\n' "${PACKAGES[@]}"
  exit 0
fi

missing=()
for p in "${PACKAGES[@]}"; do
  status=$(dpkg-query -W -f='${Status}' "$p" 2>/dev/null || true)
  [[ "$status" == "install ok installed" ]] || missing+=("$p")
done

if [[ ${#missing[@]} -eq 0 ]]; then
  echo "setup-runtime-deps: all ${#PACKAGES[@]} packages present"
  exit 0
fi
if [[ "${1:-}" == "--check" ]]; then
  echo "setup-runtime-deps: missing: ${missing[*]}" >&2
  exit 1
fi

echo "setup-runtime-deps: installing ${#missing[@]} packages: ${missing[*]}"
if [[ $(id -u) -ne 0 ]]; then SUDO=sudo; else SUDO=; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"

still=()
for p in "${missing[@]}"; do
  status=$(dpkg-query -W -f='${Status}' "$p" 2>/dev/null || true)
  [[ "$status" == "install ok installed" ]] || still+=("$p")
done
if [[ ${#still[@]} -gt 0 ]]; then
  echo "setup-runtime-deps: failed to install: ${still[*]}" >&2
  exit 1
fi
echo "setup-runtime-deps: done"
