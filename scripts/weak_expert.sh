#!/usr/bin/env bash
# The paper's kind of demonstrator, a weak learned policy: BC (lerobot-train, configs/bc_lift_lowdim.json) on a few
# episodes of a slow, noise-free scripted operator, stopped early. Deterministic on one machine (fixed seeds); its demonstrations are
# recorded with configs/record_weak_expert.yaml, whose header gives what it measured.
#   make weak-expert    # -> outputs/weak_expert/bc/checkpoints/last/pretrained_model
set -euo pipefail
cd "$(dirname "$0")/.."
export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
BIN=.venv/bin
OUT=${OUT:-outputs/weak_expert}
EPISODES=${EPISODES:-14}        # scripted episodes it learns from
SPEED=${SPEED:-0.7}             # the operator's speed (dataset_tools/noise.py): it lifts later than the expert
BC_STEPS=${BC_STEPS:-1400}      # lerobot-train steps, batch 64
# Env seeds 100,000 and up: apart from the demonstrations' (0, 1, ...), validation (2,000,000 + i) and test seeds.
if [ ! -f "$OUT/scripted/meta/info.json" ]; then
  $BIN/bcrl-record --repo_id=local/weak_expert_scripted --root="$OUT/scripted" --n_episodes="$EPISODES" \
    --demonstrators="[{speed: $SPEED}]" --seed=100000 --images=false --overwrite=true
fi
if [ ! -d "$OUT/bc/checkpoints/last/pretrained_model" ]; then
  $BIN/lerobot-train --config_path=configs/bc_lift_lowdim.json --dataset.repo_id=local/weak_expert_scripted \
    --dataset.root="$OUT/scripted" --output_dir="$OUT/bc" --steps="$BC_STEPS" --batch_size=64 --save_freq="$BC_STEPS" \
    --log_freq=500 --seed=1000 > "$OUT/lerobot_train.log" 2>&1 || { tail -n 40 "$OUT/lerobot_train.log" >&2; exit 1; }
fi
echo "weak expert: $OUT/bc/checkpoints/last/pretrained_model"
