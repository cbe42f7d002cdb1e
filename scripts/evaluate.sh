#!/usr/bin/env bash
# The paper's evaluation, regenerated: renders the held-out sequences of each
# trained environment through a live framediffuser-server (gRPC, the same path
# a game client takes), autoregressively from one ground-truth keyframe, for
# the full model and each ablation that has been trained; computes the
# autoencoder round trip of the ground truth; and writes per-environment
# results (tables, per-frame metrics, stability plot, contact sheet, side-by-
# side MP4) into docs/evaluation/<env>/, then refreshes the tables of
# docs/EVALUATION.md between its "results:<env>" markers.
#
#   scripts/evaluate.sh                 street and room, every frame
#   FD_EVAL_ENVS=street FD_EVAL_FRAMES=100 scripts/evaluate.sh   a quick look
#   FD_EVAL_SKY=previous_output ...   sky from the previous output (default:
#                         client_image, the frame's own sky, as the authors)
#   FD_EVAL_REUSE=1 ...   keep a variant's frames from an earlier run when its
#                         weights and the frame range are unchanged (a stamp
#                         of both sits beside the frames); render the rest
#   FD_EVAL_LONG=1000 ... also render the full model alone over that many
#                         consecutive frames (the temporal-stability run:
#                         docs/evaluation/<env>-long/, "results:<env>-long")
#
# Variants (each a folder; missing ones are skipped and said so):
#   <env>                environments/<env>            all three stages
#   <env>-no-scni        models/<env>-no-scni          stages 1-2 without noise injection, no stage 3
#   <env>-no-irradiance  models/<env>-no-irradiance    black irradiance in every stage
#   <env>-single-image   models/<env>-single-image     stage 1 only (X->RGB: no previous frame)
# scripts/train-environments.sh trains them.
set -euo pipefail
cd "$(dirname "$0")/.."

ENVS=${FD_EVAL_ENVS:-street room}
FRAMES=${FD_EVAL_FRAMES:-}   # empty: the whole held-out sequence
OUT=${FD_EVAL_OUT:-docs/evaluation}
WORK=${FD_EVAL_WORK:-build/evaluation}
REUSE=${FD_EVAL_REUSE:-0}
LONG=${FD_EVAL_LONG:-}
# Sky pixels (black basecolor and depth): client_image takes them from the
# frame's FinalImage, as the authors' inference and evaluation do (a game's
# skybox); previous_output fills them from the previous rendered frame.
SKY=${FD_EVAL_SKY:-client_image}
bin=build/default
scenegen=$bin/tools/scenegen/framediffuser-scenegen
server=$bin/server/framediffuser-server
client=$bin/client_sdk/framediffuser-client
evaluate=$bin/tools/evaluate/framediffuser-evaluate

cmake --preset default >/dev/null
cmake --build --preset default --target framediffuser-scenegen framediffuser-server \
  framediffuser-client framediffuser-evaluate

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

mkdir -p "$WORK"
repo=$WORK/repository
rm -rf "$repo"
mkdir -p "$repo"
declare -A variant_dir
for env in $ENVS; do
  seq=data/$env/val/seed1-0000
  if [[ ! -d $seq/FinalImage ]]; then
    # shellcheck disable=SC2046
    "$scenegen" --size 128x128 $(heldout "$env") --out "$seq" >/dev/null
  fi
  variant_dir[$env]=environments/$env
  for suffix in no-scni no-irradiance single-image; do
    variant_dir[$env-$suffix]=models/$env-$suffix
  done
done
# A variant counts once its last stage is done (its export names it).
last_stage() {
  case $1 in
    *-single-image) echo stage1 ;;
    *-no-scni) echo stage2 ;;
    *) echo stage3 ;;
  esac
}
for name in "${!variant_dir[@]}"; do
  dir=${variant_dir[$name]}
  if [[ -f $dir/environment.json ]] &&
     grep -q "\"description\": \"Trained by framediffuser-train ([^)]*$(last_stage "$name"))" "$dir/environment.json"; then
    ln -s "$(realpath "$dir")" "$repo/$name"
  fi
done

port_file=$(mktemp)
"$server" --listen 127.0.0.1:0 --port-file "$port_file" --model_repository "$repo" \
  --max_size 512 --max_steps 50 >"$WORK/server.log" 2>&1 &
server_pid=$!
trap 'kill $server_pid 2>/dev/null || true; wait $server_pid 2>/dev/null || true; rm -f "$port_file"' EXIT
for _ in $(seq 1 600); do
  [[ -s $port_file ]] && break
  kill -0 $server_pid 2>/dev/null || { echo "evaluate: server exited during start-up" >&2; cat "$WORK/server.log" >&2; exit 1; }
  sleep 0.1
done
addr="127.0.0.1:$(cat "$port_file")"
"$client" envs --server "$addr"

label() {
  case $1 in
    *-no-scni) echo "Without self-conditioning and noise injection" ;;
    *-no-irradiance) echo "Without irradiance" ;;
    *-single-image) echo "Single image (X->RGB, stage 1 only)" ;;
    *) echo "FrameDiffuser (all three stages)" ;;
  esac
}

# render NAME DIR RANGE [client flags]: NAME's frames of $seq in DIR, reused
# under FD_EVAL_REUSE=1 when a stamp says nothing they depend on changed.
render() {
  local name=$1 rendered=$2 range=$3
  shift 3
  # What the frames depend on: the variant's weights and settings, the range.
  local stamp
  stamp="$range $SKY $(cat "$repo/$name"/environment.json "$repo/$name"/*/*.safetensors | sha256sum | cut -d' ' -f1)"
  if [[ $REUSE == 1 && -f $rendered.stamp && $(cat "$rendered.stamp") == "$stamp" ]]; then
    echo "evaluate: $name ($range) unchanged since its last render; reused"
    return 0
  fi
  rm -rf "$rendered" "$rendered.stamp"
  local start end
  start=$(date +%s.%N)
  # Frame 0's keyframe is its own ground truth (the authors' inference when
  # there is no frame before); every later frame sees only model output.
  "$client" render --server "$addr" --env "$name" --input "$seq" --output "$rendered" \
    --frames "$range" --keyframe-from-input --sky-mode "$SKY" "$@" >/dev/null
  end=$(date +%s.%N)
  echo "evaluate: $name ($range) rendered in $(awk -v a="$start" -v b="$end" 'BEGIN { printf "%.1f", b - a }') s"
  echo "$stamp" >"$rendered.stamp"
}

evaluated=()
for env in $ENVS; do
  if [[ ! -e $repo/$env ]]; then
    echo "evaluate: environments/$env is not trained yet; skipped"
    continue
  fi
  evaluated+=("$env")
  seq=data/$env/val/seed1-0000
  range=${FRAMES:+0:$FRAMES}
  range=${range:-0:}
  variants=()
  for name in "$env" "$env-no-scni" "$env-no-irradiance" "$env-single-image"; do
    if [[ ! -e $repo/$name ]]; then
      echo "evaluate: $name not trained (${variant_dir[$name]} missing); skipped"
      continue
    fi
    video=()
    if [[ $name == "$env" ]] && command -v ffmpeg >/dev/null; then
      mkdir -p "$OUT/$env"
      video=(--video "$OUT/$env/side_by_side.mp4" --side-by-side)
    fi
    render "$name" "$WORK/$env/$name" "$range" "${video[@]}"
    variants+=(--variant "$(label "$name")=$WORK/$env/$name")
  done
  rt_stamp=$(sha256sum <environments/"$env"/vae/diffusion_pytorch_model.safetensors | cut -d' ' -f1)
  if [[ $REUSE == 1 && -f $WORK/$env/roundtrip.stamp && $(cat "$WORK/$env/roundtrip.stamp") == "$rt_stamp" ]]; then
    echo "evaluate: $env round trip unchanged (same VAE); reused"
  else
    rm -rf "$WORK/$env/roundtrip" "$WORK/$env/roundtrip.stamp"
    "$evaluate" roundtrip --env environments/"$env" --input "$seq" --out "$WORK/$env/roundtrip"
    echo "$rt_stamp" >"$WORK/$env/roundtrip.stamp"
  fi
  "$evaluate" report --input "$seq" --roundtrip "$WORK/$env/roundtrip" "${variants[@]}" \
    --out "$OUT/$env"
  if [[ -n $LONG ]]; then
    # The temporal-stability run: the full model alone, LONG consecutive
    # autoregressive frames from one keyframe.
    render "$env" "$WORK/$env/$env-long" "0:$LONG"
    "$evaluate" report --input "$seq" --roundtrip "$WORK/$env/roundtrip" \
      --variant "$(label "$env")=$WORK/$env/$env-long" --out "$OUT/$env-long"
    evaluated+=("$env-long")
  fi
done

# docs/EVALUATION.md: replace each "<!-- results:<env> -->" ... "<!-- /results:<env> -->"
# block with docs/evaluation/<env>/results.md.
python3 - "$OUT" "${evaluated[@]}" <<'EOF'
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
echo "evaluate: results in $OUT and docs/EVALUATION.md"
