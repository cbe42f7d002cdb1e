#!/usr/bin/env bash
# Enforces the one-way component dependencies in sources and CMake files:
#   client_sdk -> proto; server -> session -> model; server -> proto;
#   nothing in model/ or session/ uses gRPC, protobuf or prometheus;
#   client_sdk never uses model/ or session/ (nor LibTorch);
#   trainer -> model, fd::client_io; nothing depends on trainer/ or tools/;
#   tools/evaluate -> model, fd::client_io.
# A component folder that does not exist yet is skipped.
set -u
root=${1:?usage: layering_test.sh SOURCE_DIR}
cd "$root" || exit 2
fail=0
checked=0

# forbid DIR REGEX WHAT: no file under DIR may match REGEX.
forbid() {
  local dir=$1 regex=$2 what=$3
  [[ -d $dir ]] || return 0
  checked=$((checked + 1))
  local hits
  hits=$(grep -rnE --include='*.h' --include='*.cc' --include='*.cpp' \
         --include='CMakeLists.txt' --include='*.cmake' "$regex" "$dir" || true)
  if [[ -n $hits ]]; then
    echo "LAYERING VIOLATION: $what"
    echo "$hits" | sed 's/^/  /'
    fail=1
  fi
}

no_rpc='#include *[<"](grpc|grpcpp|google/protobuf|prometheus)/|gRPC::|protobuf::|prometheus-cpp::|fd::proto|fd_proto'
forbid model   "$no_rpc" "model/ must not use gRPC, protobuf or prometheus"
forbid session "$no_rpc" "session/ must not use gRPC, protobuf or prometheus"
forbid model   '#include *"(session|server|client_sdk)/|fd::(session|server|client)' \
       "model/ must not depend on session/, server/ or client_sdk/"
forbid session '#include *"(server|client_sdk)/|fd::(server|client)' \
       "session/ must not depend on server/ or client_sdk/"
forbid client_sdk '#include *[<"](model|session|server)/|#include *<torch/|fd::(model|session|server)|TORCH_LIBRARIES|Torch' \
       "client_sdk/ must depend only on proto, gRPC, abseil and image I/O"
# Nothing below the tools includes tools/ (the presets live in model/).
for dir in model session server trainer; do
  forbid "$dir" '#include *"tools/|fd::make_checkpoint|fd_make_checkpoint' \
         "$dir/ must not depend on tools/"
done
# The trainer sits on model/ and the dataset / image I/O (fd::client_io);
# nothing else depends on it, and it never uses the gRPC SDK or the server.
for dir in model session server client_sdk; do
  forbid "$dir" '#include *"trainer/|fd::trainer|fd_trainer' "$dir/ must not depend on trainer/"
done
# (fd::client_io's namespace is fd::client; the SDK target fd::client is not allowed.)
forbid trainer "$no_rpc"'|#include *"(session|server)/|fd::(session|server)|fd::client([^_:]|$)' \
       "trainer/ must depend only on model/ and the dataset I/O (fd::client_io)"
forbid trainer '#include *"client_sdk/(client|session|cli/|internal/)' \
       "trainer/ may use client_sdk's dataset/image I/O only, not the gRPC SDK"
# The evaluation tool: model/ (the VAE round trip) and fd::client_io only;
# it reaches the server through framediffuser-client, never by linking it.
forbid tools/evaluate "$no_rpc"'|#include *"(session|server|trainer)/|fd::(session|server|trainer)|fd::client([^_:]|$)' \
       "tools/evaluate/ must depend only on model/ and the image I/O (fd::client_io)"
forbid proto   '#include' "proto/ holds only .proto files (generated code, no handwritten logic)"

if [[ $checked -eq 0 ]]; then
  echo "layering: no component folder found under $root" >&2
  exit 1
fi
[[ $fail -eq 0 ]] && echo "layering: $checked rules hold"
exit $fail
