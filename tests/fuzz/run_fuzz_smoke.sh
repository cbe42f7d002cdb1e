#!/usr/bin/env bash
# Runs one fuzz target for a bounded number of executions on its seed corpus
# (ctest's fuzz.<name> tests). Works for both builds of a target: libFuzzer
# (the fuzz preset) and the standalone driver (every other preset).
#
# Usage: run_fuzz_smoke.sh <target binary> <seed corpus dir> <runs>
# libFuzzer writes new inputs to its first corpus folder and crash files to
# -artifact_prefix: both go to a temporary folder, never into the source tree.
set -euo pipefail
target=$1 seeds=$2 runs=$3
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir "$work/corpus"
# -max_len: the corpus's largest seeds are a few KiB; -rss_limit_mb keeps a
# run on a 2-core CI machine well inside its memory.
"$target" -runs="$runs" -seed=1 -max_len=65536 -rss_limit_mb=2048 -timeout=30 \
  -artifact_prefix="$work/" -print_final_stats=1 "$work/corpus" "$seeds"
