#!/usr/bin/env bash
# The method on a small default of the paper's setting (<= 15 min on 2 cores after set-up): record weak
# demonstrators (a mix of six simulated operators that fail often and lift late), BC with lerobot-train, BC+RL with
# bcrl-finetune, evaluate (bcrl-finetune's final evaluation and lerobot-eval), report.
set -euo pipefail
cd "$(dirname "$0")/.."
export MUJOCO_GL=${MUJOCO_GL:-egl} HF_HUB_OFFLINE=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
BIN=.venv/bin
OUT=${DEMO_OUT:-outputs/demo}
SEED=${DEMO_SEED:-0}
EPISODES=${DEMO_EPISODES:-60}
BC_STEPS=${DEMO_BC_STEPS:-3000}
RL_STEPS=${DEMO_RL_STEPS:-153600}
EVAL_EPISODES=${DEMO_EVAL_EPISODES:-50}
DATA="$OUT/lift_operator_mix"
DATASET="--dataset.repo_id=local/lift_operator_mix --dataset.root=$DATA"
rm -rf "$OUT/bc" "$OUT/bc_only" "$OUT/bcrl" "$OUT/eval" "$OUT/report" "$OUT/logs"
mkdir -p "$OUT/logs"

# run_logged LOG CMD...: LeRobot's CLIs log every setting; their whole output goes to LOG, and if CMD fails its
# tail is shown and the demo stops.
run_logged() {
  local log=$1
  shift
  if ! "$@" >"$log" 2>&1; then
    tail -n 40 "$log" >&2
    echo "demo: failed; the whole output is in $log" >&2
    exit 1
  fi
}
stage() { echo "== $* ($(date -u -d @$SECONDS +%M:%S) into the demo) =="; }

stage "1/5 record $EPISODES episodes of six weak operators (configs/record_operator_mix.yaml, low-dim)"
$BIN/bcrl-record --config_path=configs/record_operator_mix.yaml --root="$DATA" --n_episodes="$EPISODES" \
  --seed="$SEED" --overwrite=true

stage "2/5 BC: lerobot-train, $BC_STEPS steps"
run_logged "$OUT/logs/lerobot_train.log" \
  $BIN/lerobot-train --config_path=configs/bc_lift_lowdim.json $DATASET --output_dir="$OUT/bc" \
  --steps="$BC_STEPS" --batch_size=64 --save_freq="$BC_STEPS" --log_freq=500 --seed="$SEED"
tr '\r' '\n' < "$OUT/logs/lerobot_train.log" | grep -E "step:|End of training" | sed -E 's/^.*INFO [0-9-]+ [0-9:]+ +[^ ]+ //' || true
BC_CKPT="$OUT/bc/checkpoints/last/pretrained_model"

stage "3/5 BC+RL: bcrl-finetune with the recipe's config, $RL_STEPS env steps (and BC only, 0 env steps, for the table)"
$BIN/bcrl-finetune --config_path=configs/bcrl_lift_lowdim_best_validation.json --policy.path="$BC_CKPT" $DATASET \
  --total_env_steps=0 --final_eval_episodes="$EVAL_EPISODES" --seed="$SEED" --output_dir="$OUT/bc_only"
# the recipe, validated every 25,600 env steps instead of 12,800 to fit the demo's time
$BIN/bcrl-finetune --config_path=configs/bcrl_lift_lowdim_best_validation.json --policy.path="$BC_CKPT" $DATASET \
  --eval_freq=25600 --total_env_steps="$RL_STEPS" --final_eval_episodes="$EVAL_EPISODES" --seed="$SEED" --output_dir="$OUT/bcrl"

stage "4/5 evaluate the checkpoint the validation chose (checkpoints/best) with the unmodified lerobot-eval"
run_logged "$OUT/logs/lerobot_eval.log" \
  $BIN/lerobot-eval --policy.path="$OUT/bcrl/checkpoints/best/pretrained_model" --env.type=bcrl_lift \
  --env.obs_type=agent_pos --eval.n_episodes=4 --eval.batch_size=1 --eval.use_async_envs=false \
  --policy.device=cpu --output_dir="$OUT/eval"
$BIN/python - "$OUT/eval" <<'PY'
import json, sys
overall = json.load(open(f"{sys.argv[1]}/eval_info.json"))["overall"]
print(f"lerobot-eval: {overall['n_episodes']} episodes, mean return {overall['avg_sum_reward']:.1f},"
      f" success {overall['pc_success']:.0f} %; videos in {sys.argv[1]}/videos")
PY

stage "5/5 report: Tables 1-4, plots"
$BIN/bcrl-report --runs="[$OUT/bc_only,$OUT/bcrl]" --output_dir="$OUT/report"
stage "done"
