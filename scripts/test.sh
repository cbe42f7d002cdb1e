#!/usr/bin/env bash
# The README test command: install dependencies (apt, idempotent), configure,
# build and run every test. Fails if any step fails, any test fails, or no
# test ran (ctest preset: noTestsAction=error).
#
# Usage: scripts/test.sh [ctest args...]   e.g. scripts/test.sh -R proto
set -euo pipefail
cd "$(dirname "$0")/.."

scripts/setup-deps.sh
export CCACHE_DIR="${CCACHE_DIR:-$HOME/.cache/ccache}"
cmake --preset default
cmake --build --preset default
ctest --preset default "$@"
