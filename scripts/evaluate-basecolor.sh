#!/usr/bin/env bash
# Does a trained environment read the colours of the basecolor, or only its
# light and dark? Renders the held-out frames of each environment through a
# live framediffuser-server (gRPC, noise seed 1, the environment's default
# steps) three times: with the G-buffer as it is, with the basecolor's red
# and blue channels swapped, and with the basecolor reduced to its luma (no
# hue; ffmpeg's gray, BT.601). Every other buffer and the keyframe stay the
# same. The report compares each altered render with the unaltered one (its
# "ground truth" here): a model that follows the albedo's colours changes its
# frames where they change (low PSNR); one that reads only luminance renders
# the luma-only basecolor almost as before (high PSNR). Writes
# docs/evaluation/<env>-basecolor/ and docs/EVALUATION.md's
# "results:<env>-basecolor" block.
#
#   scripts/evaluate-basecolor.sh                     street, 150 frames
#   FD_EVAL_ENVS="street room" FD_EVAL_FRAMES=100 scripts/evaluate-basecolor.sh
#   FD_EVAL_OUT=DIR FD_EVAL_DOC=0 ...  write elsewhere, leave the doc alone
set -euo pipefail
cd "$(dirname "$0")/.."

ENVS=${FD_EVAL_ENVS:-street}
FRAMES=${FD_EVAL_FRAMES:-150}
OUT=${FD_EVAL_OUT:-docs/evaluation}
WORK=${FD_EVAL_WORK:-build/evaluation-basecolor}
DOC=${FD_EVAL_DOC:-1}
# shellcheck source=scripts/lib/evaluation.sh
source scripts/lib/evaluation.sh
command -v ffmpeg >/dev/null || { echo "evaluate-basecolor: needs ffmpeg (scripts/setup-deps.sh)" >&2; exit 1; }
eval_build

# altered_sequence SEQ DIR FILTER: SEQ's first FRAMES frames with its
# BaseColor passed through the ffmpeg video filter FILTER, the other buffers
# linked.
altered_sequence() {
  local seq=$1 dir=$2 filter=$3 buffer f
  rm -rf "$dir"
  mkdir -p "$dir/BaseColor"
  for buffer in FinalImage Normals Depth Roughness Metallic; do
    [[ -d $seq/$buffer ]] || continue
    mkdir -p "$dir/$buffer"
    for ((f = 0; f < FRAMES; f++)); do
      ln -s "$(realpath "$seq/$buffer/$(printf '%s_%04d.png' "$buffer" "$f")")" "$dir/$buffer/"
    done
  done
  ffmpeg -loglevel error -start_number 0 -i "$seq/BaseColor/BaseColor_%04d.png" -frames:v "$FRAMES" \
    -vf "$filter" -pix_fmt rgb24 -start_number 0 "$dir/BaseColor/BaseColor_%04d.png"
}

# shellcheck disable=SC2086
serve_shipped "$WORK" $ENVS

names=()
for env in $ENVS; do
  seq=$(heldout_sequence "$env")
  steps=$(environment_steps "$env")
  altered_sequence "$seq" "$WORK/$env/as-is" "null"
  altered_sequence "$seq" "$WORK/$env/red-blue" "colorchannelmixer=rr=0:rb=1:br=1:bb=0"
  altered_sequence "$seq" "$WORK/$env/luma" "format=gray,format=rgb24"
  for variant in as-is red-blue luma; do
    rm -rf "$WORK/$env/$variant-rendered"
    render_sequence "$env" "$WORK/$env/$variant" "$WORK/$env/$variant-rendered" "0:$FRAMES" \
      --sky-mode client_image --steps "$steps"
  done
  # The unaltered render takes the ground truth's place: the report's PSNR is
  # then the agreement of each altered render with it.
  reference=$WORK/$env/reference
  rm -rf "$reference"
  cp -r "$WORK/$env/red-blue" "$reference"
  rm -rf "$reference/FinalImage"
  cp -r "$WORK/$env/as-is-rendered/FinalImage" "$reference/FinalImage"
  results=$OUT/$env-basecolor
  rm -rf "$results"
  "$evaluate" report --input "$reference" \
    --variant "basecolor red and blue swapped=$WORK/$env/red-blue-rendered" \
    --variant "basecolor luma only (no hue)=$WORK/$env/luma-rendered" --out "$results" >/dev/null
  {
    echo "$env, $steps step$([[ $steps == 1 ]] || echo s) per frame: each altered render against"
    echo "the render of the unaltered G-buffer (the table's \"ground truth\"; the contact sheet's"
    echo "columns: that render | red and blue swapped | the swapped basecolor | irradiance)."
    echo
    grep -v -e "Autoencoder" -e "^Flicker" "$results/results.md"
  } >"$results/results.tmp"
  mv "$results/results.tmp" "$results/results.md"
  rm -f "$results/stability.png"
  names+=("$env-basecolor")
done
if [[ $DOC == 1 ]]; then
  refresh_doc "$OUT" "${names[@]}"
  echo "evaluate-basecolor: results in $OUT and docs/EVALUATION.md"
else
  echo "evaluate-basecolor: results in $OUT"
fi
