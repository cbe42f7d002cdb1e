#!/usr/bin/env bash
# Steps per frame, measured: renders each trained environment's held-out
# sequence through a live framediffuser-server (gRPC), autoregressively from
# one ground-truth keyframe, once per denoising step count, and writes the
# comparison (PSNR/SSIM against the ground truth and against the autoencoder
# round trip, flicker, frames/s) into docs/evaluation/<env>-steps/ and
# docs/EVALUATION.md's "results:<env>-steps" block. The shipped environments'
# default (environment.json "steps") was chosen from these tables.
#
#   scripts/evaluate-steps.sh             street (150 frames) and room (400)
#   FD_EVAL_ENVS=room FD_EVAL_STEPS_SWEEP="1 10" scripts/evaluate-steps.sh
#   FD_EVAL_FRAMES=N ...  frames per render (default: street 150, room 400,
#                         the ranges of scripts/evaluate.sh's recorded runs)
#   FD_EVAL_OUT=DIR FD_EVAL_DOC=0 ...  write elsewhere, leave the doc alone
#   FD_EVAL_ENCODE_SWEEP="1 2" ...  for an environment that reuses its
#                         previous latent ("previous_latent": "reuse"), also
#                         these step counts with the authors' VAE encode of
#                         the previous frame instead (rows "..., encoded")
set -euo pipefail
cd "$(dirname "$0")/.."

ENVS=${FD_EVAL_ENVS:-street room}
SWEEP=${FD_EVAL_STEPS_SWEEP:-1 2 3 4 6 10}
ENCODE_SWEEP=${FD_EVAL_ENCODE_SWEEP-1 2}  # set and empty: none
OUT=${FD_EVAL_OUT:-docs/evaluation}
WORK=${FD_EVAL_WORK:-build/evaluation-steps}
DOC=${FD_EVAL_DOC:-1}
SKY=${FD_EVAL_SKY:-client_image}  # the frame's own sky, as in scripts/evaluate.sh
# shellcheck source=scripts/lib/evaluation.sh
source scripts/lib/evaluation.sh
eval_build

default_frames() {
  case $1 in street) echo 150 ;; *) echo 400 ;; esac
}

# shellcheck disable=SC2086
serve_shipped "$WORK" $ENVS

names=()
for env in $ENVS; do
  seq=$(heldout_sequence "$env")
  frames=${FD_EVAL_FRAMES:-$(default_frames "$env")}
  default_steps=$(environment_steps "$env")
  variants=()
  runs=()
  for steps in $SWEEP; do runs+=("$env:$steps"); done
  if [[ -e $WORK/repository/$env-encode ]]; then
    for steps in $ENCODE_SWEEP; do runs+=("$env-encode:$steps"); done
  fi
  for run in "${runs[@]}"; do
    served=${run%:*}
    steps=${run##*:}
    rendered=$WORK/$env/steps-$steps$([[ $served == "$env" ]] || echo -encode)
    rm -rf "$rendered"
    line=$(render_sequence "$served" "$seq" "$rendered" "0:$frames" --sky-mode "$SKY" --steps "$steps")
    echo "$line"
    seconds=${line##* in }
    seconds=${seconds% s}
    fps=$(awk -v n="$frames" -v s="$seconds" 'BEGIN { printf "%.1f", n / s }')
    label="$steps step$([[ $steps == 1 ]] || echo s)"
    [[ $served == "$env" ]] || label="$label, encoded"
    label="$label, $fps frames/s"
    [[ $served == "$env" && $steps == "$default_steps" ]] && label="$label (shipped default)"
    [[ $steps == 10 ]] && label="$label (the paper's)"
    variants+=(--variant "$label=$rendered")
  done
  roundtrip "environments/$env" "$seq" "$WORK/$env/roundtrip" 1
  "$evaluate" report --input "$seq" --roundtrip "$WORK/$env/roundtrip" "${variants[@]}" \
    --out "$OUT/$env-steps"
  names+=("$env-steps")
done
if [[ $DOC == 1 ]]; then
  refresh_doc "$OUT" "${names[@]}"
  echo "evaluate-steps: results in $OUT and docs/EVALUATION.md"
else
  echo "evaluate-steps: results in $OUT"
fi
