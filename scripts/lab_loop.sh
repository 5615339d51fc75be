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
if [ ! -d "$OUT/bags/ros1" ] || [ "$(ls "$OUT/bags/ground_truth" | wc -l)" -lt 30 ]; then
  $BIN/bcrl-make-demo-bags --config_path=configs/record_lab_bags.yaml --urdf="$URDF" --out_dir="$OUT/bags"
fi
# The demonstrator itself on the 50 held-out starts the policy is evaluated on, scored by the same rig (no bags kept)
if [ ! -f "$OUT/demonstrator_heldout/outcomes.json" ]; then
  $BIN/bcrl-make-demo-bags --config_path=configs/record_lab_bags.yaml --urdf="$URDF" --formats=[] --seed=100000 \
    --n_episodes="$N_EVAL" --out_dir="$OUT/demonstrator_heldout"
fi
if [ ! -f "$OUT/dataset/meta/info.json" ]; then
  $BIN/bcrl-convert --input="$OUT/bags/ros1" --urdf="$URDF" --repo_id=local/lab_towel --root="$OUT/dataset" \
    --fps=30 --image_size=64 --overwrite=true
fi
POLICY="$OUT/bc/checkpoints/last/pretrained_model"
STEPS=$($BIN/python -c "import json; print(json.load(open('configs/bc_lab_images.json'))['steps'])")
if [ ! -d "$POLICY" ]; then
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
from lerobot.datasets.lerobot_dataset import LeRobotDataset
out = Path(sys.argv[1])
# What the arm did (the dataset's proprio-derived deltas) against what the teleoperator commanded, per 30 Hz period
dataset = LeRobotDataset("local/lab_towel", root=out / "dataset", video_backend="pyav")
actions, episode_of = np.asarray(dataset.hf_dataset["action"]), np.asarray(dataset.hf_dataset["episode_index"])
deviation, first = [], []
for episode in range(dataset.num_episodes):
    commanded = np.load(out / "bags" / "ground_truth" / f"episode_{episode:03d}.npz")["command_delta_action"][:, :3]
    done = actions[episode_of == episode][:, :3]
    n = min(len(done), len(commanded))
    moving = np.linalg.norm(commanded[:n], axis=1) > 1e-3
    deviation.append(np.linalg.norm(done[:n][moving] - commanded[:n][moving], axis=1).sum() / np.linalg.norm(commanded[:n][moving], axis=1).sum())
    first.append(np.linalg.norm(done[0]) / np.linalg.norm(commanded[0]))
print(f"recording: {dataset.num_episodes} episodes, {dataset.num_frames} frames at {dataset.fps} fps; the arm's motion per "
      f"period deviates from the command by {np.mean(deviation):.0%} of it (episodes {min(deviation):.0%}-{max(deviation):.0%}); "
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
