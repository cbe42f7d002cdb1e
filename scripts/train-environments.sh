#!/usr/bin/env bash
# Retrains the shipped environments from scratch (environments/<env>) and the
# ablations docs/EVALUATION.md compares (models/<env>-*), on this machine's
# CPU, with the commands that made the committed weights.
#
#   scripts/train-environments.sh street        # one environment and its ablations
#   scripts/train-environments.sh street room   # one after the other
#   FD_TRAIN_ABLATIONS=0 scripts/train-environments.sh room   # the model only
#   FD_KEEP_VAE=1 scripts/train-environments.sh street  # keep environments/street's VAE
#   FD_KEEP_VAE=1 FD_ABLATIONS_ONLY=1 scripts/train-environments.sh room  # the ablations alone
#
# FD_ABLATIONS_ONLY=1 retrains the ablations of the committed model: stages
# 0-1 into models/<env>-stage1 (the same flags and seed as the model's own),
# the ablations from copies of it; models/<env> and environments/<env> are
# left as they are.
#
# FD_KEEP_VAE=1 starts stage 0 from the committed environment's autoencoder
# (--vae environments/<env>) instead of retraining it: the same weights the
# from-scratch VAE run made (street: 6000 steps, 44 minutes), saved as float16.
#
# Every stage runs as four single-threaded replicas (--replicas 4), one job at
# a time: on this 2-core machine that trains 2.7-3.9x faster than one thread
# (docs/BENCHMARKS.md, "Trainer (CPU)").
# An interrupted run
# continues where it stopped when started again (the trainer's --resume;
# data generation is skipped when the folders exist). Steps:
#   1. framediffuser-scenegen: training and held-out sequences (128x128) in data/<env>/.
#   2. framediffuser-train stage0 (the VAE, its decoder fine-tuned on whole frames, the base
#      UNet), stage1 into models/<env>.
#   3. The ablations start from copies of that folder, so stages 0-1 are
#      shared and every variant is trained the same way:
#        <env>-single-image  stage 1 only (no previous frame, black irradiance)
#        <env>-no-scni       stage 2 without noise injection, no stage 3
#        <env>-no-irradiance stages 2-3 with black irradiance
#   4. framediffuser-train all (stages 2-3) into models/<env>; its fp16 export
#      is copied into environments/<env> (what the server embeds / serves).
set -euo pipefail
cd "$(dirname "$0")/.."

ENVS=${*:-street room}
ABLATIONS=${FD_TRAIN_ABLATIONS:-1}
ABLATIONS_ONLY=${FD_ABLATIONS_ONLY:-0}
[[ $ABLATIONS_ONLY == 1 ]] && ABLATIONS=1
KEEP_VAE=${FD_KEEP_VAE:-0}
bin=build/default
scenegen=$bin/tools/scenegen/framediffuser-scenegen
train=$bin/trainer/framediffuser-train

cmake --preset default >/dev/null
cmake --build --preset default --target framediffuser-scenegen framediffuser-train

generate() {  # generate DIR scenegen-args...
  local dir=$1
  shift
  [[ -f $dir/scene.json ]] && return 0
  "$scenegen" --size 128x128 --out "$dir.partial" "$@" >/dev/null
  rm -rf "$dir"
  mv "$dir.partial" "$dir"
}

# The camera paths: street's loop is 2421 frames, room's 811. Held out: the
# first 1000 street frames (400 room frames) of layout seed 1, which the demo
# and the evaluation render; training: the rest of seed 1's loop and other
# layout seeds (other object placement and colours).
# Street: every layout seed follows the same camera loop, so with few layouts
# a model can learn what each camera pose shows instead of reading the
# G-buffer (with seeds 2 and 3 as whole loops it painted seed 2's and 3's
# green trees where seed 1's basecolor is orange). So street trains on 20
# more layouts, 280 frames each, their windows staggered by 112 frames round
# the loop (docs/EVALUATION.md, "What changed in the sixth round").
data_street() {
  generate data/street/val/seed1-0000 --scene street --seed 1 --start 0 --frames 1000
  generate data/street/train/seed1-1000 --scene street --seed 1 --start 1000 --frames 1421
  local seed start
  for seed in $(seq 2 21); do
    start=$(((seed - 2) * 112))
    generate "data/street/train/seed$seed-$(printf %04d "$start")" --scene street --seed "$seed" \
      --start "$start" --frames 280
  done
}
data_room() {
  generate data/room/val/seed1-0000 --scene room --seed 1 --start 0 --frames 400
  generate data/room/train/seed1-0400 --scene room --seed 1 --start 400 --frames 411
  for seed in 2 3 4 5; do
    generate data/room/train/seed$seed --scene room --seed $seed --start 0 --frames 811
  done
}

# The recipe (docs/EVALUATION.md, "How the environments were trained").
# Every command repeats every stage's flags: environment.json's record of a
# stage trained before this code kept its settings falls back to them.
# Stages 1-3 as long as street's fifth and room's second round (twice the
# first rounds' steps, docs/EVALUATION.md); street's stages 2-3 twice that
# since its seventh round (conditioned_steps).
flags() {  # flags ENV
  local vae=(--latent_channels 4 --vae_crop 64 --vae_steps "$(vae_steps "$1")" --vae_warmup 50)
  [[ $KEEP_VAE == 1 ]] && vae=(--vae "environments/$1")
  local decoder=(--decoder_steps "$(decoder_steps "$1")" --decoder_lr 2e-4)
  echo --data "data/$1/train" --val "data/$1/val" \
    --preset compact --resolution 128x128 "${vae[@]}" "${decoder[@]}" --base_steps 1500 \
    --stage1_steps 4000 --stage2_steps "$(conditioned_steps "$1" 2)" \
    --stage3_steps "$(conditioned_steps "$1" 3)" --stage1_lr 5e-4 --stage1_unet_lr 2e-4 \
    --stage2_lr 1e-3 --selfcond_steps 10 --inference_steps "$(inference_steps "$1")" \
    --checkpoint_every 250 --export_dtype float16 --sky_mode previous_output --no-progress \
    --prediction_type v_prediction
}
# UniPC steps per frame of the trainer's validation renders and its export,
# chosen by measurement (docs/EVALUATION.md, "Steps per frame": every count
# from 1 to 10 rendered through the server; fewer steps scored higher and
# flickered less than the authors' 10). The ablations export the same count;
# scripts/evaluate.sh renders every variant at FD_EVAL_STEPS (10, the
# paper's) all the same. The shipped folders then get serving_settings.
inference_steps() {  # inference_steps ENV
  case $1 in street) echo 2 ;; *) echo 1 ;; esac
}
# The shipped serving settings, written into the export after training
# (docs/EVALUATION.md, "Steps per frame"): 1 UniPC step for both, and
# "previous_latent": "reuse" (each frame's denoised latent stands in for the
# VAE encode of the previous output: as good on held-out frames, a third
# less time per frame). Street trains and validates at 2 steps, as its
# recorded commands say, and serves at 1: with the latent reused, 1 step
# scored within 0.06 dB of 2 and flickered less.
# Street's ControlNet residuals are scaled by 1.3 (docs/EVALUATION.md, "The
# ControlNet's conditioning scale": chosen on an unseen layout, +0.2 dB
# there and on the held-out frames); room keeps 1.0, which scored best.
serving_settings() {  # serving_settings ENV ENV_DIR
  local scale=1.0
  [[ $1 == street ]] && scale=1.3
  python3 -c 'import json, sys
d = json.load(open(sys.argv[1])); d["steps"] = 1; d["previous_latent"] = "reuse"
if float(sys.argv[2]) != 1.0: d["conditioning_scale"] = float(sys.argv[2])
json.dump(d, open(sys.argv[1], "w"), indent=2, sort_keys=True); open(sys.argv[1], "a").write("\n")' \
    "$2/environment.json" "$scale"
}
# Stages 2-3 (the previous-frame path): street's seventh round trains them
# twice as long as room's (docs/EVALUATION.md, "What changed in the seventh
# round"): at 1200 + 600 steps its single-image baseline (stage 1 alone)
# scored above the full model on held-out frames.
conditioned_steps() {  # conditioned_steps ENV STAGE: stage 3 is half of stage 2
  local steps=1200
  [[ $1 == street ]] && steps=2400
  [[ $2 == 3 ]] && steps=$((steps / 2))
  echo "$steps"
}
vae_steps() {  # vae_steps ENV: street's frames (thin poles, edges) need longer
  case $1 in street) echo 6000 ;; *) echo 4000 ;; esac
}
# The decoder is then fine-tuned on whole frames, its encoder frozen
# (stage0-decoder, in `stage0` between the VAE and the base UNet, so every
# ablation copied after stage 1 decodes with it): the crops' autoencoder
# bounded street's PSNR (docs/EVALUATION.md, "What changed in the eighth
# round"); room's, far from limiting, still gained 1.8 dB of round trip
# from half as many steps. The shipped weights had it after stage 3
# instead (the encoder, and so every latent, is the same either way).
decoder_steps() {  # decoder_steps ENV
  case $1 in street) echo 3000 ;; *) echo 1500 ;; esac
}
# Every diffusion stage predicts v, not the noise (docs/EVALUATION.md, "What
# changed in the third round": the noise-prediction loss hardly trains the
# highest-noise steps, where every sampler starts). Stages 0-1 draw their
# timesteps uniformly (the authors'); stages 2-3 draw them cubically (more
# high-noise steps, where a frame's layout is decided).
conditioned=(--timestep_sampling cubic)

run() {  # run COMMAND OUT [extra flags]: resumes an interrupted stage
  local command=$1 out=$2
  shift 2
  local resume=()
  [[ -f $out/checkpoints/LATEST ]] && resume=(--resume)
  # shellcheck disable=SC2046
  "$train" "$command" $(flags "$env") --replicas 4 --out "$out" "${resume[@]}" "$@"
}

for env in $ENVS; do
  case $env in
    street) data_street ;;
    room) data_room ;;
    *) echo "train-environments: unknown environment '$env' (street, room)" >&2; exit 2 ;;
  esac
  main=models/$env
  [[ $ABLATIONS_ONLY == 1 ]] && main=models/$env-stage1
  run stage0 "$main"
  run stage1 "$main"
  if [[ $ABLATIONS == 1 ]]; then
    for suffix in single-image no-scni no-irradiance; do
      if [[ ! -d models/$env-$suffix ]]; then
        # From the folder as stage 1 left it (before stage 2 writes into it).
        [[ -f $main/controllora/pytorch_lora_weights.safetensors ]] &&
          { echo "train-environments: $main is past stage 1; cannot copy it for $suffix" >&2; exit 1; }
        cp -r "$main" "models/$env-$suffix"
      fi
    done
    run stage1 "models/$env-single-image"  # its export: stage 1 alone
    [[ $ABLATIONS_ONLY == 1 ]] || run all "$main" "${conditioned[@]}"
    run stage2 "models/$env-no-scni" "${conditioned[@]}" --max_noise_sigma 0
    run all "models/$env-no-irradiance" "${conditioned[@]}" --no-irradiance
  else
    run all "$main" "${conditioned[@]}"
  fi
  [[ $ABLATIONS_ONLY == 1 ]] && continue
  rm -rf "environments/$env.new"
  mkdir -p "environments/$env.new"
  cp -r "$main"/{unet,controlnet,vae,controllora,scheduler,prompt_embeds.safetensors,environment.json} \
    "environments/$env.new/"
  serving_settings "$env" "environments/$env.new"
  rm -rf "environments/$env"
  mv "environments/$env.new" "environments/$env"
  echo "train-environments: $env -> environments/$env ($(du -sh "environments/$env" | cut -f1))"
done
