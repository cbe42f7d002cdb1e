#!/usr/bin/env bash
# Shows that tests/layering_test.sh catches what it is meant to: copies the
# component folders to a scratch tree, checks that the copy passes, then
# plants one wrong dependency at a time and expects the check to fail and to
# name the planted file.
set -euo pipefail
root=${1:?usage: layering_planted_test.sh SOURCE_DIR}
check="$root/tests/layering_test.sh"
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT

for dir in base model session server client_sdk trainer tools bench proto; do
  [[ -d $root/$dir ]] && cp -r "$root/$dir" "$scratch/$dir"
done
if ! "$check" "$scratch" >/dev/null; then
  echo "FAIL: the unmodified copy does not pass"; "$check" "$scratch"; exit 1
fi

failures=0
# plant FILE LINE: appends LINE to FILE in a fresh copy, expects a violation.
plant() {
  local file=$1 line=$2
  cp "$scratch/$file" "$scratch/$file.orig"
  echo "$line" >>"$scratch/$file"
  local out rc=0
  out=$("$check" "$scratch") || rc=$?
  mv "$scratch/$file.orig" "$scratch/$file"
  if [[ $rc -ne 1 || $out != *"$file"* ]]; then
    echo "FAIL: '$line' in $file was not reported (exit $rc)"
    failures=$((failures + 1))
  else
    echo "ok: '$line' in $file -> $(echo "$out" | head -1)"
  fi
}

plant model/pipeline/frame_pipeline.cc '#include "server/server.h"'
plant model/pipeline/frame_pipeline.cc '#include "session/session.h"'
plant model/networks/unet.cc '#include <grpcpp/grpcpp.h>'
plant base/status_macros.h '#include "model/runtime/torch_call.h"'
plant base/status_macros.h '#include <torch/types.h>'
plant session/session.cc '#include "server/log.h"'
plant session/session.cc '#include "framediffuser/v1/render_service.pb.h"'
plant server/server.cc '#include "trainer/trainer.h"'
plant server/server.cc '#include "client_sdk/client.h"'
plant server/server.cc '#include "model/pipeline/environment.h"'
plant server/render_stream.cc '#include <torch/types.h>'
plant server/CMakeLists.txt 'target_link_libraries(fd_server PRIVATE fd::model)'
plant client_sdk/client.cc '#include "model/pipeline/environment.h"'
plant client_sdk/client.cc '#include <torch/types.h>'
plant trainer/trainer.cc '#include "session/session.h"'
plant trainer/trainer.cc '#include "client_sdk/client.h"'
plant tools/evaluate/evaluation.cc '#include "server/server.h"'
plant bench/model_bench.cc '#include "tests/testing/golden.h"'
plant model/CMakeLists.txt 'target_link_libraries(fd_model PRIVATE fd::session)'
plant session/CMakeLists.txt 'target_link_libraries(fd_session PRIVATE gRPC::grpc++)'

[[ $failures -eq 0 ]] && echo "layering: every planted violation was reported"
exit $((failures > 0))
