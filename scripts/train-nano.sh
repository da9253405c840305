#!/usr/bin/env bash
# The recgen-nano training recipe (README §Training): synthetic data, the four
# trainable parts in order, then the held-out evaluation. Every step is
# deterministic for its seed; steps and batch sizes are the ones the shipped
# weights were trained with (override with the environment variables below).
#
#   bash scripts/train-nano.sh [WORK_DIR]      (default: runs/nano)
#
# On 2 CPU cores the whole run takes a few hours; the logs are in WORK_DIR/*.log.
set -euo pipefail
cd "$(dirname "$0")/.."
W=${1:-runs/nano}
RECON=${RECON:-target/release/recon}
VAE_STEPS=${VAE_STEPS:-1000}
FLOW_STEPS=${FLOW_STEPS:-1000}
AE_STEPS=${AE_STEPS:-600}
S2_STEPS=${S2_STEPS:-400}
FLOW2_STEPS=${FLOW2_STEPS:-3000}
S2B_STEPS=${S2B_STEPS:-500}
FLOW3_STEPS=${FLOW3_STEPS:-2000}
CONFIG=models/recgen-nano.json
mkdir -p "$W"
[ -x "$RECON" ] || cargo build --release

# 1. Training scenes: 400 occluded tabletop scenes, two views each, stereo-like depth noise.
[ -d "$W/data" ] || "$RECON" synth --out "$W/data" --scenes 400 --views 2 --seed 1000 --sensor models/sensors/stereo.json
D=(--data "$W/data" --split "$W/data/test" --config "$CONFIG" --seed 0)

# 2. Sparse-structure VAE on surface shells (the SLat support of stage 2).
[ -f "$W/vae/recon-train.json" ] && grep -q '"complete"' "$W/vae/recon-train.json" ||
  "$RECON" train ss-vae "${D[@]}" --out "$W/vae" --steps "$VAE_STEPS" --batch 8 --fill surface 2>&1 | tee "$W/vae.log"

# 3. Stage-2 autoencoder (independent of 2): SLat encoder + mesh/Gaussian decoders on exact SDF and colours.
[ -f "$W/slat-ae/recon-train.json" ] && grep -q '"complete"' "$W/slat-ae/recon-train.json" ||
  "$RECON" train slat-ae "${D[@]}" --out "$W/slat-ae" --steps "$AE_STEPS" --batch 2 --crop 8 --max-voxels 256 2>&1 | tee "$W/slat-ae.log"

# 4. Image encoder + SS flow with pose tokens on the VAE latents.
[ -f "$W/ss-flow/recon-train.json" ] && grep -q '"complete"' "$W/ss-flow/recon-train.json" ||
  "$RECON" train ss-flow "${D[@]}" --out "$W/ss-flow" --vae "$W/vae" --fill surface --steps "$FLOW_STEPS" --batch 8 2>&1 | tee "$W/ss-flow.log"

# 5. SLat flow on the frozen encoder's latents; writes the complete model folder.
[ -f "$W/model/recon-train.json" ] && grep -q '"complete"' "$W/model/recon-train.json" ||
  "$RECON" train slat-flow "${D[@]}" --out "$W/model" --stage1 "$W/ss-flow" --slat-ae "$W/slat-ae" --steps "$S2_STEPS" --batch 4 --max-models 600 2>&1 | tee "$W/slat-flow.log"

# 6. Second phase (the shipped weights): the pose was not learned at α = 0.01 in a CPU-sized run
#    (pose MSE stayed near its start), so ss-flow continues from step 5's weights with α = 1,
#    and the SLat flow continues on the new image encoder with more models.
[ -f "$W/ss-flow2/recon-train.json" ] && grep -q '"complete"' "$W/ss-flow2/recon-train.json" ||
  "$RECON" train ss-flow "${D[@]}" --out "$W/ss-flow2" --init "$W/ss-flow" --pose-alpha 1.0 --vae "$W/vae" --fill surface --steps "$FLOW2_STEPS" --batch 8 2>&1 | tee "$W/ss-flow2.log"
[ -f "$W/model2/recon-train.json" ] && grep -q '"complete"' "$W/model2/recon-train.json" ||
  "$RECON" train slat-flow "${D[@]}" --out "$W/model2" --init "$W/model" --stage1 "$W/ss-flow2" --slat-ae "$W/slat-ae" --steps "$S2B_STEPS" --batch 4 --max-models 1000 2>&1 | tee "$W/slat-flow2.log"

# 7. Third phase (the shipped weights): 2000 more ss-flow steps (α = 1, data seed 1, one thread),
#    then model3 = model2 with this run's image encoder and SS flow (the SLat flow and decoders are
#    model2's: stage 2 reads its geometry from the occupancy, see README §Evaluation).
[ -f "$W/ss-flow3/recon-train.json" ] && grep -q '"complete"' "$W/ss-flow3/recon-train.json" ||
  "$RECON" train ss-flow --data "$W/data" --split "$W/data/test" --config "$CONFIG" --seed 1 --threads 1 \
    --out "$W/ss-flow3" --init "$W/ss-flow2" --pose-alpha 1.0 --vae "$W/vae" --fill surface --steps "$FLOW3_STEPS" --batch 8 2>&1 | tee "$W/ss-flow3.log"
if [ ! -d "$W/model3" ]; then
  cp -r "$W/model2" "$W/model3.tmp" && rm -rf "$W/model3.tmp/checkpoints"
  cp "$W/ss-flow3/image_cond_model.safetensors" "$W/ss-flow3/ss_flow.safetensors" "$W/model3.tmp/"
  mv "$W/model3.tmp" "$W/model3"
fi

# 8. Held-out evaluation: scenes from seeds never used in training. heldout: one view per scene;
#    heldout2: two views per scene (single view, two views with pose selection, best of 3 seeds).
[ -d "$W/heldout" ] || "$RECON" synth --out "$W/heldout" --scenes 45 --views 1 --seed 90000 --sensor models/sensors/stereo.json
[ -d "$W/heldout2" ] || "$RECON" synth --out "$W/heldout2" --scenes 24 --views 2 --seed 91000 --sensor models/sensors/stereo.json
"$RECON" eval --dataset "$W/heldout2/test" --method observed --out "$W/eval2-observed" | tee "$W/eval2-observed.txt"
"$RECON" eval --dataset "$W/heldout2/test" --method recgen --weights "$W/model3" --seed 0 --max-faces 20000 --out "$W/eval2-recgen" | tee "$W/eval2-recgen.txt"
# Two views: scenes 0–11 (half the frames; two views cost more than one), next to one view on them.
S12=0,1,2,3,4,5,6,7,8,9,10,11
"$RECON" eval --dataset "$W/heldout2/test" --method recgen --weights "$W/model3" --seed 0 --max-faces 20000 --two-view --scenes $S12 --out "$W/eval2-recgen-2view" | tee "$W/eval2-recgen-2view.txt"
"$RECON" eval --dataset "$W/heldout2/test" --predictions "$W/eval2-recgen/predictions.json" --scenes $S12 --all-frames --out "$W/eval2-recgen-s12" | tee "$W/eval2-recgen-s12.txt"
"$RECON" eval --dataset "$W/heldout2/test" --predictions "$W/eval2-observed/predictions.json" --scenes $S12 --all-frames --out "$W/eval2-observed-s12" | tee "$W/eval2-observed-s12.txt"
# Best of 3 seeds costs 3× the time: scenes 0–1 only, next to the single-seed predictions re-scored on them.
S4=0,1
"$RECON" eval --dataset "$W/heldout2/test" --method recgen --weights "$W/model3" --seed 0 --max-faces 20000 --samples 3 --scenes $S4 --out "$W/eval2-recgen-best3" | tee "$W/eval2-recgen-best3.txt"
"$RECON" eval --dataset "$W/heldout2/test" --predictions "$W/eval2-recgen/predictions.json" --scenes $S4 --all-frames --out "$W/eval2-recgen-s4" | tee "$W/eval2-recgen-s4.txt"
"$RECON" eval --dataset "$W/heldout2/test" --predictions "$W/eval2-observed/predictions.json" --scenes $S4 --all-frames --out "$W/eval2-observed-s4" | tee "$W/eval2-observed-s4.txt"
# Real frames (YCB-Video, shipped with the data in ../shared/realdata when present).
YCB=${YCB:-../shared/realdata/ycbv_video_oprb}
if [ -d "$YCB" ]; then
  "$RECON" eval --dataset "$YCB" --method observed --out "$W/eval-ycb-observed" | tee "$W/eval-ycb-observed.txt"
  "$RECON" eval --dataset "$YCB" --method recgen --weights "$W/model3" --seed 0 --max-faces 20000 --out "$W/eval-ycb-recgen" | tee "$W/eval-ycb-recgen.txt"
fi
