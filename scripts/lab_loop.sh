#!/usr/bin/env bash
# The simulated lab loop: ~30 teleoperated demonstrations recorded through the real robot's command path as ROS 1
# bags, converted with bcrl-convert, the image policy trained with lerobot-train, then run back through the command
# path on the simulated rig: at the dataset's fps, and at the paper's mismatched rates (20 Hz against 30 Hz data).
# Usage: make lab-loop [URDF=path/to/sawyer.urdf]. Each stage is skipped when its output exists (rerun to resume).
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
OUT=${OUT:-outputs/lab}
URDF=${URDF:-../shared/robots/sawyer/sawyer.urdf}
N_EVAL=${N_EVAL:-50}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MUJOCO_GL=${MUJOCO_GL:-egl}

if [ ! -f "$URDF" ]; then echo "lab-loop: URDF not found: $URDF (set URDF=...)" >&2; exit 2; fi
# bcrl-make-demo-bags keeps the episodes a folder already holds (recorded with the same settings) and adds the rest
$BIN/bcrl-make-demo-bags --config_path=configs/record_lab_bags.yaml --urdf="$URDF" --out_dir="$OUT/bags"
# The demonstrator itself on the 50 held-out starts the policy is evaluated on, scored by the same rig (no bags kept)
$BIN/bcrl-make-demo-bags --config_path=configs/record_lab_bags.yaml --urdf="$URDF" --formats=[] --seed=100000 \
  --n_episodes="$N_EVAL" --out_dir="$OUT/demonstrator_heldout"
if [ ! -f "$OUT/dataset/meta/info.json" ]; then
  # poses from the bags' pose topic (the grip site); the tool offset makes forward kinematics give the same point
  $BIN/bcrl-convert --input="$OUT/bags/ros1" --urdf="$URDF" --repo_id=local/lab_towel --root="$OUT/dataset" \
    --tool_offset_pos_m="[0,0,0.109]" --tool_offset_quat_xyzw="[0,0,-0.7071068,0.7071068]" \
    --fps=30 --image_size=64 --overwrite=true
fi
POLICY="$OUT/bc/checkpoints/last/pretrained_model"
STEPS=$($BIN/python -c "import json; print(json.load(open('configs/bc_lab_images.json'))['steps'])")
if [ ! -d "$POLICY" ]; then
  rm -rf "$OUT/bc"  # a training killed before its first checkpoint: start again
  $BIN/lerobot-train --config_path=configs/bc_lab_images.json --dataset.root="$OUT/dataset" --output_dir="$OUT/bc"
elif [ "$($BIN/python -c "import json; print(json.load(open('$POLICY/../training_state/training_step.json'))['step'])")" -lt "$STEPS" ]; then
  $BIN/lerobot-train --resume=true --config_path="$POLICY/train_config.json"  # an interrupted training continues
fi
# run_fps:command_fps. 30:30 is the dataset's rate. 20:30: the policy answers at 20 Hz while the command path
# still carries out each delta in 1/30 s of velocity (1.5x every step). 20:20: loop and commands agree, but each
# delta learnt at 30 Hz now takes 1/20 s (the arm at 2/3 of the demonstrated speed).
for rates in 30:30 20:30 20:20; do
  run=${rates%:*}; cmd=${rates#*:}; dir="$OUT/eval_run${run}_cmd${cmd}"
  if [ ! -f "$dir/eval_info.json" ]; then
    $BIN/bcrl-eval-rig --policy_path="$POLICY" --urdf="$URDF" --n_episodes="$N_EVAL" --run_fps="$run" \
      --command_fps="$cmd" --allow_rate_mismatch=true --output_dir="$dir"
  fi
done
$BIN/python - "$OUT" <<'PY'
import json, sys
from pathlib import Path
import numpy as np
from dataset_tools.make_demo_bags import commanded_and_done_m
out = Path(sys.argv[1])
# What the arm did in each 30 Hz period against what the teleoperator commanded for it
deviation, first = [], []
for truth_file in sorted((out / "bags" / "ground_truth").glob("episode_*.npz")):
    commanded, done = commanded_and_done_m(np.load(truth_file))
    moving = np.linalg.norm(commanded, axis=1) > 1e-3
    deviation.append(np.linalg.norm(done[moving] - commanded[moving], axis=1).sum() / np.linalg.norm(commanded[moving], axis=1).sum())
    first.append(np.linalg.norm(done[0]) / np.linalg.norm(commanded[0]))
print(f"recording: {len(deviation)} episodes; the arm's motion per period deviates from the command by "
      f"{np.mean(deviation):.0%} of it (episodes {min(deviation):.0%}-{max(deviation):.0%}); "
      f"in the first period it covers {np.mean(first):.0%} of the commanded delta")
print(f"{'':>14} {'run Hz':>7} {'cmd Hz':>7} {'reach':>6} {'grasp':>6} {'lift':>6} {'median closest (cm)':>19}")
d = json.loads((out / "demonstrator_heldout" / "outcomes.json").read_text())
print(f"{'demonstrator':>14} {30:7g} {30:7g} {d['reached_success']:6.0%} {d['grasped_success']:6.0%} "
      f"{d['lifted_success']:6.0%} {100 * d['median_closest_approach_m']:19.1f}")
for path in sorted(out.glob("eval_run*/eval_info.json"), key=lambda p: p.parent.name, reverse=True):
    info = json.loads(path.read_text())
    a, r = info["aggregated"], info["rates"]
    print(f"{'BC (images)':>14} {r['run_fps']:7g} {r['command_fps']:7g} {a['reached_success']:6.0%} {a['grasped_success']:6.0%} "
          f"{a['lifted_success']:6.0%} {100 * a['median_closest_approach_m']:19.1f}")
PY
