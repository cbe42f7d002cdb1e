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
#   FD_EVAL_STEPS=N ...  denoising steps per frame for every render (10, the
#                         paper's; scripts/evaluate-steps.sh sweeps them)
#   FD_EVAL_LONG=1000 ... also render the full model alone over that many
#                         consecutive frames (the temporal-stability run:
#                         docs/evaluation/<env>-long/, "results:<env>-long")
#
# Variants (each a folder; missing ones are skipped and said so):
#   <env>                environments/<env>            all three stages
#   <env>-no-scni        models/<env>-no-scni          stages 1-2 without noise injection, no stage 3
#   <env>-no-irradiance  models/<env>-no-irradiance    black irradiance in every stage
#   <env>-single-image   models/<env>-single-image     stage 1 only (X->RGB: no previous frame)
# scripts/train-environments.sh trains them. Every variant renders with the
# authors' inference settings (the VAE encode of the previous frame,
# conditioning scale 1), also one whose environment.json serves otherwise
# (the shipped "previous_latent": "reuse", street's conditioning_scale).
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
# Denoising steps per frame for every variant: the paper's 10 (UniPC, the
# authors' inference), so the ablations compare as in the paper; the shipped
# environments default to fewer (scripts/evaluate-steps.sh measures why).
STEPS=${FD_EVAL_STEPS:-10}
# shellcheck source=scripts/lib/evaluation.sh
source scripts/lib/evaluation.sh
eval_build

mkdir -p "$WORK"
repo=$WORK/repository
rm -rf "$repo"
mkdir -p "$repo"
declare -A variant_dir
for env in $ENVS; do
  heldout_sequence "$env" >/dev/null
  variant_dir[$env]=environments/$env
  for suffix in no-scni no-irradiance single-image; do
    variant_dir[$env-$suffix]=models/$env-$suffix
  done
done
# A variant counts once its last stage is done (its export names it; a
# decoder fine-tune after it, stage0-decoder, may follow in the list).
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
     grep -q "\"description\": \"Trained by framediffuser-train ([^)]*$(last_stage "$name")[,)]" "$dir/environment.json"; then
    if ! authors_settings "$dir"; then
      # The paper's tables compare the variants on the authors' inference:
      # the VAE encodes each previous frame, conditioning scale 1
      # (scripts/evaluate-steps.sh measures the shipped settings).
      with_settings "$dir" "$repo/$name" previous_latent='"encode"' conditioning_scale=1.0
    else
      ln -s "$(realpath "$dir")" "$repo/$name"
    fi
  fi
done

start_server "$repo" "$WORK/server.log"

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
  stamp="$range $SKY $STEPS $(cat "$repo/$name"/environment.json "$repo/$name"/*/*.safetensors | sha256sum | cut -d' ' -f1)"
  if [[ $REUSE == 1 && -f $rendered.stamp && $(cat "$rendered.stamp") == "$stamp" ]]; then
    echo "evaluate: $name ($range) unchanged since its last render; reused"
    return 0
  fi
  rm -rf "$rendered" "$rendered.stamp"
  render_sequence "$name" "$seq" "$rendered" "$range" --sky-mode "$SKY" --steps "$STEPS" "$@"
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
  roundtrip "environments/$env" "$seq" "$WORK/$env/roundtrip" "$REUSE"
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

# docs/EVALUATION.md: each "<!-- results:<env> -->" block from docs/evaluation/<env>/.
refresh_doc "$OUT" "${evaluated[@]}"
echo "evaluate: results in $OUT and docs/EVALUATION.md"
