#!/usr/bin/env bash
# The paper's experiments for one sigma, low-dim (CPU) or images (GPU): record demonstrations, BC with
# lerobot-train, then "BC only", BC+RL and PPO from scratch with bcrl-finetune (each ends with a deterministic
# evaluation on the same held-out test seeds), and the report (tables, plots). Every choice comes from configs/ but
# the image BC+RL's critic, a policy field that bcrl-finetune takes from the BC checkpoint and --policy.* flags
# only; otherwise this script only chains the commands and sets sizes.
#   SIGMA=0.01 bash scripts/experiments.sh            # or: make experiments SIGMA=0.01
# Another training seed on the same demonstrations: BC_NAME=bc_seed2 BC_ARGS="--seed=2" (BC) and/or
# BCRL_NAME=bcrl_seed2 BCRL_ARGS="--seed=2" (PPO); the report puts the runs of one cell (every $OUT/bcrl*) together.
# A finished step whose output exists is skipped; a killed BC+RL or scratch run resumes from its last checkpoint.
set -euo pipefail
cd "$(dirname "$0")/.."
export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
BIN=.venv/bin
SIGMA=${SIGMA:-0.1}
MODE=${MODE:-lowdim}                      # lowdim | images
if [ "$MODE" = lowdim ]; then
  RECORD_CONFIG=configs/record_lowdim_retry.yaml         # 100 episodes, 30 % planned misses with retries
  BCRL_CONFIG=${BCRL_CONFIG:-configs/bcrl_lift_lowdim_best_validation.json}
  # 102,400 env steps (the config's); at sigma 0.1 the validation return was still rising there, and the runs
  # measured in docs/RESULTS.md went on to 204,800.
  DEFAULT_RL_STEPS=$([ "$SIGMA" = 0.1 ] && echo 204800 || echo 102400)
  DEFAULT_EPISODES=100; DEFAULT_BC_STEPS=3000
  CRITIC_ARGS=""
else
  RECORD_CONFIG=configs/record_sigma${SIGMA}.yaml
  BCRL_CONFIG=${BCRL_CONFIG:-configs/bcrl_lift_images.json}
  DEFAULT_RL_STEPS=297600
  DEFAULT_EPISODES=50; DEFAULT_BC_STEPS=20000  # the record config's and configs/bc_lift_images.json's
  # the asymmetric critic (the simulator's state; the actor still acts on pixels): docs/RESULTS.md, "Image BC+RL on
  # the CPU", compares it with the critic on the image keypoints
  CRITIC_ARGS="--policy.critic_observation=privileged"
fi
OUT=${OUT:-outputs/experiments/${MODE}_sigma${SIGMA}}
EPISODES=${EPISODES:-$DEFAULT_EPISODES}    # demonstrations
BC_STEPS=${BC_STEPS:-$DEFAULT_BC_STEPS}    # lerobot-train steps
BC_ARGS=${BC_ARGS:-}                      # extra lerobot-train flags, e.g. "--seed=2"
RL_STEPS=${RL_STEPS:-$DEFAULT_RL_STEPS}   # env steps of BC+RL
SCRATCH_STEPS=${SCRATCH_STEPS:-297600}    # env steps of PPO from scratch (0: skip it)
EVAL_EPISODES=${EVAL_EPISODES:-50}        # test episodes of every final evaluation
BCRL_ARGS=${BCRL_ARGS:-}                  # extra bcrl-finetune flags for the BC+RL run, e.g. "--seed=2"
BC_NAME=${BC_NAME:-bc}                    # the BC checkpoint's folder under $OUT (trained if missing)
BC_ONLY_NAME=${BC_ONLY_NAME:-bc_only}     # its "BC only" evaluation's folder
BCRL_NAME=${BCRL_NAME:-bcrl}              # the BC+RL run's folder under $OUT
DATA="$OUT/data"
DATASET="--dataset.repo_id=local/lift_${MODE}_sigma${SIGMA} --dataset.root=$DATA"
mkdir -p "$OUT"

if [ ! -f "$DATA/meta/info.json" ]; then
  echo "== record $EPISODES episodes, sigma=$SIGMA ($MODE) =="
  $BIN/bcrl-record --config_path="$RECORD_CONFIG" --repo_id="local/lift_${MODE}_sigma${SIGMA}" --root="$DATA" \
    --n_episodes="$EPISODES" --sigma="$SIGMA" --seed=0 --overwrite=true
fi
BC_CKPT="$OUT/$BC_NAME/checkpoints/last/pretrained_model"
if [ ! -d "$BC_CKPT" ]; then
  echo "== BC: lerobot-train, $BC_STEPS steps =="
  $BIN/lerobot-train --config_path="configs/bc_lift_${MODE}.json" $DATASET --output_dir="$OUT/$BC_NAME" \
    --steps="$BC_STEPS" --save_freq="$BC_STEPS" --log_freq=500 $BC_ARGS
fi
finetune() {  # finetune <run name> <args...>: run, or resume a killed run, or skip a finished one
  local name=$1; shift
  [ -f "$OUT/$name/eval_final.json" ] && return 0
  local resume=false; [ -e "$OUT/$name/checkpoints/last" ] && resume=true
  echo "== $name =="
  $BIN/bcrl-finetune "$@" $DATASET --final_eval_episodes="$EVAL_EPISODES" --output_dir="$OUT/$name" --resume=$resume
}
finetune "$BC_ONLY_NAME" --config_path="$BCRL_CONFIG" --policy.path="$BC_CKPT" --total_env_steps=0
finetune "$BCRL_NAME" --config_path="$BCRL_CONFIG" --policy.path="$BC_CKPT" --total_env_steps="$RL_STEPS" $CRITIC_ARGS $BCRL_ARGS
RUNS="$OUT/$BC_ONLY_NAME,$OUT/bcrl*"
if [ "$SCRATCH_STEPS" != 0 ]; then
  finetune scratch --config_path="configs/ppo_scratch_lift_${MODE}.json" --policy.type=bcrl --total_env_steps="$SCRATCH_STEPS"
  RUNS="$RUNS,$OUT/scratch"
fi
$BIN/bcrl-report --runs="[$RUNS]" --output_dir="$OUT/report"
