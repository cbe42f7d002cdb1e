#!/usr/bin/env bash
# Enforces the one-way component dependencies (README "Layout") in sources
# and CMake files. Two kinds of rule:
#
#  1. Which project folders a component may include ("#include "<folder>/"),
#     one line per component below. Its own folder is always allowed; proto/
#     is included as "framediffuser/v1/..." (the generated code).
#  2. Which third-party libraries and CMake targets it may use (gRPC,
#     protobuf, prometheus, LibTorch), and a few finer rules inside a
#     component's allowed set (the trainer uses client_sdk's dataset I/O only).
#
# A component folder that does not exist is skipped. Exit status 1 on any
# violation (each printed with file:line), 2 on usage errors.
# tests/layering_planted_test.sh checks that a planted wrong include fails.
set -u
root=${1:?usage: layering_test.sh SOURCE_DIR}
cd "$root" || exit 2
fail=0
checked=0
sources=(--include='*.h' --include='*.cc' --include='*.cpp')
cmake_files=(--include='CMakeLists.txt' --include='*.cmake')

# Every top-level folder that holds includable project code.
project_folders=(base model session server client_sdk trainer tools bench tests framediffuser)

violation() {
  echo "LAYERING VIOLATION: $1"
  echo "$2" | sed 's/^/  /'
  fail=1
}

# allow DIR "FOLDER..." : files under DIR include only DIR itself and FOLDERs.
allow() {
  local dir=$1 allowed=" $2 "
  [[ -d $dir ]] || return 0
  checked=$((checked + 1))
  local own=${dir%%/*} folder hits
  for folder in "${project_folders[@]}"; do
    [[ $folder == "$own" || $allowed == *" $folder "* ]] && continue
    hits=$(grep -rnE "${sources[@]}" "#include *[<\"]$folder/" "$dir" || true)
    [[ -n $hits ]] && violation "$dir/ may include only: ${2:-nothing outside itself} (found $folder/)" "$hits"
  done
  return 0
}

# forbid DIR REGEX WHAT [cmake]: no source (and CMake file) under DIR matches.
forbid() {
  local dir=$1 regex=$2 what=$3
  [[ -d $dir ]] || return 0
  checked=$((checked + 1))
  local hits
  # Comment lines ("// ..." in C++, "# ..." in CMake) do not count.
  hits=$(grep -rnE "${sources[@]}" "${cmake_files[@]}" "$regex" "$dir" |
         grep -vE '^[^:]+:[0-9]+:[[:space:]]*(//|# )' || true)
  [[ -n $hits ]] && violation "$what" "$hits"
  return 0
}

# 1. Include rules, bottom to top.
allow base                 ""
allow model                "base"
allow session              "base model"
allow server               "base session framediffuser"
allow client_sdk           "base framediffuser"
allow trainer              "base model client_sdk"
allow tools/make_checkpoint "base model"
allow tools/evaluate       "base model client_sdk"
allow tools/scenegen       "base client_sdk"
allow bench                "base model session server client_sdk trainer tools framediffuser"
allow proto                ""

# 2. Third-party libraries and CMake targets.
no_rpc='#include *[<"](grpc|grpcpp|google/protobuf|prometheus)/|gRPC::|protobuf::|prometheus-cpp::|fd::proto|fd_proto'
no_torch='#include *<(torch|ATen|c10)/|TORCH_LIBRARIES|find_package\(Torch'
forbid base    "$no_rpc|$no_torch|fd::(model|session|server|client|trainer)" "base/ uses abseil only"
forbid model   "$no_rpc|fd::(session|server|client|trainer)|fd_(session|server|client|trainer)" \
       "model/ must not use gRPC, protobuf, prometheus or a component above it"
forbid session "$no_rpc|fd::(server|client|trainer)|fd_(server|client|trainer)" \
       "session/ must not use gRPC, protobuf, prometheus or a component above it"
forbid client_sdk "$no_torch|fd::(model|session|server|trainer)" \
       "client_sdk/ must depend only on proto, gRPC, abseil and image I/O"
# The server reaches the model only through session/: no tensors, no model
# types by name (session/compute_runtime.h names what it passes through).
forbid server "$no_torch|model::|fd::model|fd_model" \
       "server/ must not use LibTorch or model/ (session/ is the only layer below it)"
# Nothing below the tools and benchmarks uses them.
for dir in base model session server client_sdk trainer; do
  forbid "$dir" 'fd::make_checkpoint|fd_make_checkpoint|fd::evaluate|fd::scenegen' \
         "$dir/ must not depend on tools/"
done
# Nothing depends on the trainer but its benchmark.
for dir in base model session server client_sdk tools; do
  forbid "$dir" 'fd::trainer|fd_trainer' "$dir/ must not depend on trainer/"
done
# (fd::client_io's namespace is fd::client; the SDK target fd::client is not allowed.)
forbid trainer "$no_rpc"'|fd::(session|server)|fd::client([^_:]|$)' \
       "trainer/ must depend only on model/ and the dataset I/O (fd::client_io)"
forbid trainer '#include *"client_sdk/(client|session|cli/|internal/)' \
       "trainer/ may use client_sdk's dataset/image I/O only, not the gRPC SDK"
# The evaluation tool reaches the server through framediffuser-client, never
# by linking it.
forbid tools/evaluate "$no_rpc"'|fd::(session|server|trainer)|fd::client([^_:]|$)' \
       "tools/evaluate/ must depend only on model/ and the image I/O (fd::client_io)"
forbid tools/evaluate '#include *"client_sdk/(client|session|cli/|internal/)' \
       "tools/evaluate/ may use client_sdk's image I/O only, not the gRPC SDK"
forbid proto '#include' "proto/ holds only .proto files (generated code, no handwritten logic)"
# Benchmarks never reach into the tests' helpers.
forbid bench 'fd::testing|fd_testing|tests/testing' "bench/ must not use tests/ helpers"

if [[ $checked -eq 0 ]]; then
  echo "layering: no component folder found under $root" >&2
  exit 1
fi
[[ $fail -eq 0 ]] && echo "layering: $checked rules hold"
exit $fail
