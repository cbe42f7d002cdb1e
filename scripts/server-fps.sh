#!/usr/bin/env bash
# Frames/s of the embedded default environment (street) through a live
# framediffuser-server: one client session, then SESSIONS concurrent ones, on
# a framediffuser-scenegen street sequence at the environment's 128x128, with
# the server's peak RSS after each phase (docs/BENCHMARKS.md, "The shipped
# street environment"). A benchmark, not a test: nothing is asserted.
#
# Usage: [FD_FPS_FRAMES=60] [FD_FPS_SESSIONS=4] [FD_FPS_ENV=default] scripts/server-fps.sh \
#          [server flags...]
# FD_FPS_ENV names another environment to render (served with, say,
# --model_repository DIR among the server flags).
# Needs a built default preset (cmake --build --preset default).
set -euo pipefail
cd "$(dirname "$0")/.."

frames=${FD_FPS_FRAMES:-60}
sessions=${FD_FPS_SESSIONS:-4}
env=${FD_FPS_ENV:-default}
bin=build/default
work=$(mktemp -d)
port_file="$work/port"

"$bin/tools/scenegen/framediffuser-scenegen" --scene street --frames "$frames" --size 128x128 \
  --seed 1 --out "$work/input" >/dev/null 2>&1
"$bin/server/framediffuser-server" --listen 127.0.0.1:0 --port-file "$port_file" "$@" \
  2>"$work/server.log" &
server_pid=$!
trap 'kill $server_pid 2>/dev/null || true; wait $server_pid 2>/dev/null || true; rm -rf "$work"' EXIT
for _ in $(seq 1 600); do
  [[ -s $port_file ]] && break
  kill -0 "$server_pid" 2>/dev/null || { echo "server-fps: server exited" >&2; exit 1; }
  sleep 0.1
done
addr="127.0.0.1:$(cat "$port_file")"
# A repository's environments load in the background: wait until none is
# still loading.
for _ in $(seq 1 600); do
  "$bin/client_sdk/framediffuser-client" envs --server "$addr" 2>/dev/null | grep -q -i loading || break
  sleep 0.2
done

render() {
  "$bin/client_sdk/framediffuser-client" render --server "$addr" --env "$env" \
    --input "$work/input" --output "$work/out$1" --keyframe-from-input \
    --sky-mode client_image >"$work/client$1.log" 2>&1
}
memory() { grep -E 'VmHWM|VmRSS' "/proc/$server_pid/status" | tr -s ' \t\n' ' '; }

echo "server after start: $(memory)"
render warmup
echo "after one warm-up session: $(memory)"
for n in 1 "$sessions"; do
  start=$(date +%s.%N)
  pids=()
  for i in $(seq 1 "$n"); do
    render "$i" &
    pids+=($!)
  done
  wait "${pids[@]}"
  end=$(date +%s.%N)
  echo "sessions $n: $((n * frames)) frames in $(echo "$end - $start" | bc) s =" \
    "$(echo "scale=2; $n * $frames / ($end - $start)" | bc) frames/s; server $(memory)"
done
grep -E '"event":"(intra_op_threads|server_start)"' "$work/server.log" || true
