#!/usr/bin/env bash
# Installs every build, test and demo dependency of FrameDiffuser Server from
# Debian 12 packages. Idempotent: when everything is present it only checks
# (dpkg-query) and returns in well under a second; it never downloads anything
# but Debian packages.
#
# Usage: scripts/setup-deps.sh [--check]   (--check: report missing, exit 1)
set -euo pipefail

# One package per line, grouped by what needs it. Keep in sync with README.
PACKAGES=(
  # toolchain and build speed
  build-essential cmake ninja-build ccache mold pkg-config git
  # model/: LibTorch (CPU) with a fast BLAS instead of reference BLAS, and
  # Sleef's header for the fused CPU attention kernel (model/runtime/)
  libtorch-dev libopenblas0-pthread libsleef-dev
  # wire API and server
  libgrpc++-dev protobuf-compiler-grpc protobuf-compiler libprotobuf-dev
  libabsl-dev prometheus-cpp-dev
  # config, compression, images
  nlohmann-json3-dev libzstd-dev libpng-dev libjpeg-dev libopenexr-dev
  # zlib: the image tests write raw PNG chunks (CRC32)
  zlib1g-dev
  # tests and benchmarks
  libgtest-dev libgmock-dev libbenchmark-dev
  # interop tests (Python stubs from our proto), metrics checks, videos
  python3 python3-grpcio python3-protobuf prometheus ffmpeg
  # scale-out integration test and deploy/ config checks (issue 9)
  nginx python3-yaml
  # the fuzz preset: clang with libFuzzer and the sanitizer runtimes (issue 19)
  clang libclang-rt-14-dev
)

missing=()
for p in "${PACKAGES[@]}"; do
  status=$(dpkg-query -W -f='${Status}' "$p" 2>/dev/null || true)
  [[ "$status" == "install ok installed" ]] || missing+=("$p")
done

if [[ ${#missing[@]} -eq 0 ]]; then
  echo "setup-deps: all ${#PACKAGES[@]} packages present"
  exit 0
fi
if [[ "${1:-}" == "--check" ]]; then
  echo "setup-deps: missing: ${missing[*]}" >&2
  exit 1
fi

echo "setup-deps: installing ${#missing[@]} packages: ${missing[*]}"
if [[ $(id -u) -ne 0 ]]; then SUDO=sudo; else SUDO=; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
# --no-install-recommends keeps the image lean; every runtime need is listed.
$SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"

# Re-check so a package that apt silently skipped fails here, not later.
still=()
for p in "${missing[@]}"; do
  status=$(dpkg-query -W -f='${Status}' "$p" 2>/dev/null || true)
  [[ "$status" == "install ok installed" ]] || still+=("$p")
done
if [[ ${#still[@]} -gt 0 ]]; then
  echo "setup-deps: failed to install: ${still[*]}" >&2
  exit 1
fi
echo "setup-deps: done"
