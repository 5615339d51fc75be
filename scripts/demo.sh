#!/usr/bin/env bash
# The main job on a small default: record noisy expert demonstrations of Lift and summarise them.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
OUT=${DEMO_OUT:-outputs/demo}
EPISODES=${DEMO_EPISODES:-10}
SIGMA=${DEMO_SIGMA:-0.1}
mkdir -p "$OUT"
echo "== 1/2 record $EPISODES noisy expert episodes (sigma=$SIGMA, 128x128 camera, video) =="
.venv/bin/bcrl-record --repo_id=local/lift_sigma$SIGMA --root="$OUT/lift_sigma$SIGMA" \
  --n_episodes="$EPISODES" --sigma="$SIGMA" --seed=0 --overwrite=true
echo "== 2/2 load it back with LeRobotDataset and summarise =="
$PY -m dataset_tools.summary --root="$OUT/lift_sigma$SIGMA"
$PY - "$OUT/lift_sigma$SIGMA" <<'PY'
import sys
from lerobot.datasets.lerobot_dataset import LeRobotDataset
ds = LeRobotDataset("local/demo", root=sys.argv[1])
frame = ds[0]
print(f"LeRobotDataset: {ds.num_episodes} episodes, {ds.num_frames} frames; frame 0 keys: {sorted(k for k in frame if not k.startswith('task'))}")
PY
