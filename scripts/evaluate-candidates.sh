#!/usr/bin/env bash
# Is a training round's model better than the shipped one? Serves trained
# environment folders that are not shipped (a round's models/<name>, a stage's
# train/last-<stage>/) through one live framediffuser-server (gRPC), each with
# its own weights and the serving settings its spec gives, beside the shipped
# environments/ENV at its own settings, renders ENV's held-out frames
# autoregressively from one ground-truth keyframe (noise seed 1, the frame's
# own sky, as scripts/evaluate.sh), and reports PSNR / SSIM against the ground
# truth and against the first candidate's autoencoder round trip, and flicker.
# The docs' "Tried in a ... round" tables measure the same way.
#
#   scripts/evaluate-candidates.sh OUT NAME=DIR[,FIELD=VALUE...] ...
#   scripts/evaluate-candidates.sh build/cl \
#       avg=models/street-cl,steps=1,conditioning_scale=1.3,previous_latent=reuse \
#       last=models/street-cl/train/last-stage3,steps=1,conditioning_scale=1.3,previous_latent=reuse
#
#   FD_EVAL_ENV=room ...     the environment whose held-out frames render (street)
#   FD_EVAL_FRAMES=N ...     frames 0..N-1 (default 150)
#   FD_EVAL_SHIPPED=0 ...    leave the shipped environment out of the report
#   FD_EVAL_WORK=DIR ...     renders and round trips (build/evaluation-candidates)
#
# FIELD=VALUE replaces an environment.json field (steps, conditioning_scale,
# previous_latent, ...; VALUE is JSON, or a string). The "vs AE" columns of
# every row, the shipped one's too, are against the first candidate's round
# trip, kept while that VAE is unchanged. Writes OUT/results.md (printed), metrics.json,
# per_frame.csv, stability.png and contact_sheet.png (the first candidate).
set -euo pipefail
cd "$(dirname "$0")/.."

usage() {
  sed -n '12,21p' "$0" | sed 's/^# \{0,1\}//' >&2
  exit 2
}
[[ $# -ge 2 ]] || usage
OUT=$1
shift
ENV=${FD_EVAL_ENV:-street}
FRAMES=${FD_EVAL_FRAMES:-150}
SHIPPED=${FD_EVAL_SHIPPED:-1}
WORK=${FD_EVAL_WORK:-build/evaluation-candidates}
# shellcheck source=scripts/lib/evaluation.sh
source scripts/lib/evaluation.sh

names=()
dirs=()
fields=()
for spec in "$@"; do
  [[ $spec == *=* ]] || usage
  name=${spec%%=*}
  rest=${spec#*=}
  dir=${rest%%,*}
  [[ $name =~ ^[A-Za-z0-9_-]+$ && $name != shipped ]] ||
    { echo "evaluate-candidates: bad candidate name '$name' (letters, digits, - and _; not 'shipped')" >&2; exit 2; }
  [[ -f $dir/environment.json ]] ||
    { echo "evaluate-candidates: $name: $dir is not an environment folder (no environment.json)" >&2; exit 2; }
  names+=("$name")
  dirs+=("$dir")
  if [[ $rest == *,* ]]; then fields+=("${rest#*,}"); else fields+=(""); fi
done
eval_build

mkdir -p "$WORK"
rm -rf "$WORK/repository"
mkdir -p "$WORK/repository"
for i in "${!names[@]}"; do
  IFS=, read -r -a replaced <<<"${fields[$i]}"
  with_settings "${dirs[$i]}" "$WORK/repository/${names[$i]}" "${replaced[@]}"
done
[[ $SHIPPED == 1 ]] && ln -s "$(realpath "environments/$ENV")" "$WORK/repository/shipped"
start_server "$WORK/repository" "$WORK/server.log"

seq=$(heldout_sequence "$ENV")
variants=()
[[ $SHIPPED == 1 ]] && names+=(shipped)
for name in "${names[@]}"; do
  rendered=$WORK/$ENV-$name-$FRAMES
  rm -rf "$rendered"
  render_sequence "$name" "$seq" "$rendered" "0:$FRAMES" --sky-mode client_image
  variants+=(--variant "$name=$rendered")
done

# The first candidate's round trip, kept while its VAE's weights are the same.
roundtrip "${dirs[0]}" "$seq" "$WORK/$ENV-roundtrip" 1
"$evaluate" report --input "$seq" --roundtrip "$WORK/$ENV-roundtrip" "${variants[@]}" --out "$OUT"
cat "$OUT/results.md"
