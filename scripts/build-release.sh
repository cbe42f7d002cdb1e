#!/usr/bin/env bash
# Builds the release binaries with the README's preset (tests off) and stages
# them into PREFIX/bin: what the build stage of deploy/docker/Dockerfile.cpu
# runs, so that the image holds exactly what this script produces here.
#
# Usage: scripts/build-release.sh [--build-dir DIR] [--prefix DIR] [--no-build]
#   --build-dir DIR  CMake build folder (default build/release)
#   --prefix DIR     where bin/ is staged (default /opt/framediffuser)
#   --no-build       only stage from an existing build folder (tests use this)
# Dependencies come from scripts/setup-deps.sh (run it first).
set -euo pipefail
cd "$(dirname "$0")/.."

build_dir=build/release
prefix=/opt/framediffuser
do_build=1
while [[ $# -gt 0 ]]; do
  case "$1" in
    --build-dir) build_dir=$2; shift 2 ;;
    --prefix) prefix=$2; shift 2 ;;
    --no-build) do_build=0; shift ;;
    *) echo "build-release: unknown argument '$1' (see the header of $0)" >&2; exit 2 ;;
  esac
done

# The binaries an image needs: the server, the CLI (health checks, render,
# eval) and the scene generator (smoke tests with generated sequences).
TARGETS=(
  server/framediffuser-server
  client_sdk/framediffuser-client
  tools/scenegen/framediffuser-scenegen
)

if [[ $do_build -eq 1 ]]; then
  cmake --preset default -B "$build_dir" -DFD_BUILD_TESTS=OFF
  cmake --build "$build_dir" --target "${TARGETS[@]##*/}"
fi

mkdir -p "$prefix/bin"
for t in "${TARGETS[@]}"; do
  src="$build_dir/$t"
  if [[ ! -x "$src" ]]; then
    echo "build-release: $src is missing; build it (or drop --no-build)" >&2
    exit 1
  fi
  install -m 0755 "$src" "$prefix/bin/"
  # Smaller images; symbols stay in the build folder.
  strip --strip-unneeded "$prefix/bin/${t##*/}"
done
echo "build-release: staged ${#TARGETS[@]} binaries in $prefix/bin"
