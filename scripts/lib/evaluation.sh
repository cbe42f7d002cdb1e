# shellcheck shell=bash
# Shared by the scripts/evaluate*.sh scripts (sourced, not
# run): the held-out sequences, a live server on a model repository, one
# autoregressive render through it, and the refresh of docs/EVALUATION.md's
# result blocks. Callers set `set -euo pipefail` and cd to the repository.

eval_bin=build/default
scenegen=$eval_bin/tools/scenegen/framediffuser-scenegen
server=$eval_bin/server/framediffuser-server
client=$eval_bin/client_sdk/framediffuser-client
evaluate=$eval_bin/tools/evaluate/framediffuser-evaluate

eval_build() {
  cmake --preset default >/dev/null
  cmake --build --preset default --target framediffuser-scenegen framediffuser-server \
    framediffuser-client framediffuser-evaluate
}

# The held-out sequences (never trained on; scripts/train-environments.sh uses
# the same commands): street frames 0-999 of its layout seed 1 (training
# covers 1000-2420 and other seeds); room frames 0-399 of seed 1.
heldout() {
  case $1 in
    street) echo "--scene street --seed 1 --start 0 --frames 1000" ;;
    room) echo "--scene room --seed 1 --start 0 --frames 400" ;;
    *) echo "unknown environment $1" >&2; return 1 ;;
  esac
}

# heldout_sequence ENV: prints the held-out sequence's folder, generating it
# when missing.
heldout_sequence() {
  local seq=data/$1/val/seed1-0000
  if [[ ! -d $seq/FinalImage ]]; then
    # shellcheck disable=SC2046
    "$scenegen" --size 128x128 $(heldout "$1") --out "$seq" >/dev/null
  fi
  echo "$seq"
}

# serve_shipped WORK ENV...: a server (start_server) on a model repository
# WORK/repository that links the shipped environments/ENV folders, and, for
# an environment that reuses its previous latent, ENV-encode: the same
# weights with the authors' VAE encode of the previous frame.
serve_shipped() {
  local work=$1 env
  shift
  mkdir -p "$work"
  rm -rf "$work/repository"
  mkdir -p "$work/repository"
  for env in "$@"; do
    ln -s "$(realpath "environments/$env")" "$work/repository/$env"
    if [[ $(previous_latent "environments/$env") == reuse ]]; then
      with_settings "environments/$env" "$work/repository/$env-encode" previous_latent='"encode"'
    fi
  done
  start_server "$work/repository" "$work/server.log"
}

# previous_latent DIR: the environment folder's "previous_latent" ("encode"
# when environment.json does not say).
previous_latent() {
  python3 -c 'import json, sys; print(json.load(open(sys.argv[1])).get("previous_latent", "encode"))' \
    "$1/environment.json"
}

# with_settings SRC DST KEY=VALUE...: a folder DST serving SRC's weights (its
# entries linked) with the given environment.json fields replaced, e.g.
# previous_latent='"encode"' conditioning_scale=1.0; a VALUE that is not
# JSON is a string (previous_latent=encode).
with_settings() {
  local src entry dst=$2
  src=$(realpath "$1")
  shift 2
  rm -rf "$dst"
  mkdir -p "$dst"
  for entry in "$src"/*; do
    [[ $(basename "$entry") == environment.json ]] || ln -s "$entry" "$dst/"
  done
  python3 -c 'import json, sys
d = json.load(open(sys.argv[1]))
for field in sys.argv[3:]:
    key, value = field.split("=", 1)
    try:
        d[key] = json.loads(value)
    except ValueError:
        d[key] = value
json.dump(d, open(sys.argv[2], "w"), indent=2)' "$src/environment.json" "$dst/environment.json" "$@"
}

# authors_settings DIR: true when DIR's environment.json serves with the
# authors' inference settings that scripts/evaluate.sh compares variants at
# (the VAE encode of the previous frame, ControlNet conditioning scale 1).
authors_settings() {
  python3 -c 'import json, sys
d = json.load(open(sys.argv[1]))
sys.exit(0 if d.get("previous_latent", "encode") == "encode" and d.get("conditioning_scale", 1.0) == 1.0 else 1)' \
    "$1/environment.json"
}

# environment_steps ENV: the shipped environment's default denoising steps
# per frame (environment.json "steps").
environment_steps() {
  python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["steps"])' \
    "environments/$1/environment.json"
}

# start_server REPOSITORY LOG: a server on a free loopback port, in the
# background, stopped when the calling script exits; sets $addr once it
# listens and every environment of REPOSITORY has loaded.
start_server() {
  local port_file
  port_file=$(mktemp)
  "$server" --listen 127.0.0.1:0 --port-file "$port_file" --model_repository "$1" \
    --max_size 512 --max_steps 50 >"$2" 2>&1 &
  server_pid=$!
  trap 'kill $server_pid 2>/dev/null || true; wait $server_pid 2>/dev/null || true' EXIT
  for _ in $(seq 1 600); do
    [[ -s $port_file ]] && break
    kill -0 "$server_pid" 2>/dev/null || { echo "evaluate: server exited during start-up" >&2; cat "$2" >&2; exit 1; }
    sleep 0.1
  done
  addr="127.0.0.1:$(cat "$port_file")"
  rm -f "$port_file"
  # Environments load in the background: wait until none is still loading.
  for _ in $(seq 1 600); do
    "$client" envs --server "$addr" | grep -q -i "loading" || break
    sleep 0.2
  done
  "$client" envs --server "$addr"
}

# render_sequence ENV_NAME SEQ OUT RANGE [client flags]: the autoregressive
# render through the server. Frame 0's keyframe is its own ground truth (the
# authors' inference when there is no frame before); every later frame sees
# only model output. Noise seed 1 unless the flags give --seed (the CLI
# would draw a random one, and a rerun would move the figures by a few
# hundredths of a dB). Prints the wall time.
render_sequence() {
  local name=$1 seq=$2 rendered=$3 range=$4
  shift 4
  local start end
  start=$(date +%s.%N)
  "$client" render --server "$addr" --env "$name" --input "$seq" --output "$rendered" \
    --frames "$range" --keyframe-from-input --seed 1 "$@" >/dev/null
  end=$(date +%s.%N)
  echo "evaluate: $name ($range ${*}) rendered in $(awk -v a="$start" -v b="$end" 'BEGIN { printf "%.1f", b - a }') s"
}

# roundtrip ENV_DIR SEQ DIR REUSE: the autoencoder round trip of SEQ's ground
# truth through the environment folder ENV_DIR's VAE into DIR; with REUSE=1
# kept from an earlier run when a stamp says the VAE is the same.
roundtrip() {
  local env=$1 seq=$2 dir=$3 reuse=$4 stamp
  stamp=$(sha256sum <"$env/vae/diffusion_pytorch_model.safetensors" | cut -d' ' -f1)
  if [[ $reuse == 1 && -f $dir.stamp && $(cat "$dir.stamp") == "$stamp" ]]; then
    echo "evaluate: $env round trip unchanged (same VAE); reused"
    return 0
  fi
  rm -rf "$dir" "$dir.stamp"
  "$evaluate" roundtrip --env "$env" --input "$seq" --out "$dir"
  echo "$stamp" >"$dir.stamp"
}

# refresh_doc OUT NAME...: docs/EVALUATION.md's "<!-- results:NAME -->" ...
# "<!-- /results:NAME -->" blocks replaced by OUT/NAME/results.md.
refresh_doc() {
  python3 - "$@" <<'EOF'
import pathlib, re, sys
out, envs = pathlib.Path(sys.argv[1]), sys.argv[2:]
doc = pathlib.Path("docs/EVALUATION.md")
text = doc.read_text()
for env in envs:
    table = (out / env / "results.md").read_text()
    pattern = re.compile(r"(<!-- results:%s -->\n).*?(<!-- /results:%s -->)" % (env, env), re.S)
    if not pattern.search(text):
        sys.exit("docs/EVALUATION.md has no results:%s block" % env)
    text = pattern.sub(lambda m: m.group(1) + table + m.group(2), text)
doc.write_text(text)
EOF
}
