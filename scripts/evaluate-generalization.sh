#!/usr/bin/env bash
# Does a trained environment read the G-buffer, or remember its training
# frames? Renders the same layout (seed 1) of each environment through a live
# framediffuser-server (gRPC), at the environment's default steps per frame,
# on two windows of equal length: its held-out frames (the first frames of
# the loop, never trained on) and the first frames of the loop's trained part
# (scripts/train-environments.sh trains on them). A model that renders the
# second far better than the first has learnt its training frames, not the
# mapping from G-buffer to light. Writes docs/evaluation/<env>-generalization/
# and docs/EVALUATION.md's "results:<env>-generalization" block.
#
#   scripts/evaluate-generalization.sh          street and room, 150 frames each
#   FD_EVAL_ENVS=street FD_EVAL_FRAMES=100 scripts/evaluate-generalization.sh
#   FD_EVAL_OUT=DIR FD_EVAL_DOC=0 ...  write elsewhere, leave the doc alone
set -euo pipefail
cd "$(dirname "$0")/.."

ENVS=${FD_EVAL_ENVS:-street room}
FRAMES=${FD_EVAL_FRAMES:-150}
OUT=${FD_EVAL_OUT:-docs/evaluation}
WORK=${FD_EVAL_WORK:-build/evaluation-generalization}
DOC=${FD_EVAL_DOC:-1}
SKY=${FD_EVAL_SKY:-client_image}  # the frame's own sky, as in scripts/evaluate.sh
# shellcheck source=scripts/lib/evaluation.sh
source scripts/lib/evaluation.sh
eval_build

# The first trained frame of layout seed 1's loop (scripts/train-environments.sh).
first_trained_frame() {
  case $1 in street) echo 1000 ;; room) echo 400 ;; *) echo "unknown environment $1" >&2; return 1 ;; esac
}

# shellcheck disable=SC2086
serve_shipped "$WORK" $ENVS

names=()
for env in $ENVS; do
  heldout_sequence "$env" >/dev/null
  first=$(first_trained_frame "$env")
  (( FRAMES <= first )) || { echo "evaluate-generalization: FD_EVAL_FRAMES must be <= $first for $env" >&2; exit 2; }
  steps=$(environment_steps "$env")
  results=$OUT/$env-generalization
  mkdir -p "$results"
  : >"$WORK/$env.results.md"
  for window in heldout trained; do
    if [[ $window == heldout ]]; then
      start=0 what="held out, never trained on"
    else
      start=$first what="trained on"
    fi
    # The window's frames, made again by the scene generator (deterministic:
    # the same pixels the trainer or the evaluation read).
    seq=$WORK/$env/$window-sequence
    if [[ ! -f $seq/scene.json ]]; then
      rm -rf "$seq"
      "$scenegen" --size 128x128 --scene "$env" --seed 1 --start "$start" --frames "$FRAMES" \
        --out "$seq" >/dev/null
    fi
    rendered=$WORK/$env/$window
    rm -rf "$rendered"
    render_sequence "$env" "$seq" "$rendered" "$start:" --sky-mode "$SKY" --steps "$steps"
    rm -rf "$WORK/$env/$window-roundtrip"
    "$evaluate" roundtrip --env "environments/$env" --input "$seq" --out "$WORK/$env/$window-roundtrip" \
      >/dev/null
    "$evaluate" report --input "$seq" --roundtrip "$WORK/$env/$window-roundtrip" \
      --variant "$env, $steps step$([[ $steps == 1 ]] || echo s) per frame=$rendered" \
      --out "$results/$window"
    { echo "**Layout seed 1, frames $start–$((start + FRAMES - 1)) ($what):**"; echo;
      cat "$results/$window/results.md"; echo; } >>"$WORK/$env.results.md"
  done
  mv "$WORK/$env.results.md" "$results/results.md"
  names+=("$env-generalization")
done
if [[ $DOC == 1 ]]; then
  refresh_doc "$OUT" "${names[@]}"
  echo "evaluate-generalization: results in $OUT and docs/EVALUATION.md"
else
  echo "evaluate-generalization: results in $OUT"
fi
