"""scripts/experiments.sh (`make experiments`) at a tiny size: in low-dim mode it runs the recipe of docs/RESULTS.md
(retry demonstrations, BC from configs/bc_lift_lowdim.json, BC+RL from the best-validation config), and its steps
chain into a report."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from lerobot_bcrl.rl.checkpoint import FINETUNE_CONFIG_NAME

ROOT = Path(__file__).resolve().parents[1]

# sizes only: every choice of the recipe comes from the script's defaults
TINY = {
    "EPISODES": "2", "BC_STEPS": "4", "RL_STEPS": "128", "SCRATCH_STEPS": "0", "EVAL_EPISODES": "1",
    "BCRL_ARGS": "--rollout.n_workers=0 --rollout.envs_per_worker=1 --rollout.steps_per_env=64 --eval_freq=64"
                 " --eval_episodes=1 --save_freq=64 --env.episode_length=40 --ppo.minibatch_size=32"
                 " --bc_batch_size=32 --tensorboard=false",
}


@pytest.mark.slow
def test_experiments_script_runs_the_recipe_by_default(tmp_path):
    out = tmp_path / "sigma0"
    env = {**os.environ, **TINY, "SIGMA": "0", "OUT": str(out)}
    for choice in ("BC_ARGS", "BCRL_CONFIG"):
        env.pop(choice, None)  # the script's own defaults, not the caller's
    result = subprocess.run(["bash", "scripts/experiments.sh"], cwd=ROOT, env=env, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, (result.stdout + result.stderr)[-4000:]

    recorded = json.loads((out / "data" / "meta" / "bcrl.json").read_text())["record_config"]
    assert recorded["sigma"] == 0 and recorded["images"] is False and recorded["n_episodes"] == 2
    assert recorded["miss_probability"] == 0.3 and recorded["reopen_on_empty_grasp"] is True
    assert recorded["miss_height_range_m"] == [0.015, 0.045] and recorded["miss_max_aside_m"] == 0.035

    bc = json.loads((out / "bc" / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text())
    assert bc["rotation_weight"] == 1.0 and bc["critic_hidden_dims"] == [256, 256]
    assert bc["input_features"]["observation.environment_state"]["shape"] == [13]  # with the cube-yaw features

    bcrl = json.loads((out / "bcrl" / "checkpoints" / "last" / "pretrained_model" / FINETUNE_CONFIG_NAME).read_text())
    assert bcrl["select"] == "best_validation" and bcrl["schedule"]["theta_min"] == 0.0
    assert bcrl["ppo"]["reset_log_std"] == -1.5 and bcrl["ppo"]["term_weighting"] == "gradient_share"
    final = json.loads((out / "bcrl" / "eval_final.json").read_text())
    assert final["env_steps"] == 128 and final["selected_env_steps"] in (0, 64, 128)
    assert json.loads((out / "bc_only" / "eval_final.json").read_text())["method"] == "BC"
    report = (out / "report" / "report.md").read_text()
    assert "BC+RL" in report and "Table 1" in report


@pytest.mark.slow
def test_weak_expert_script_makes_a_checkpoint_that_records_the_weak_expert_config(tmp_path):
    out = tmp_path / "weak_expert"
    env = {**os.environ, "OUT": str(out), "EPISODES": "1", "BC_STEPS": "2"}
    result = subprocess.run(["bash", "scripts/weak_expert.sh"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert result.returncode == 0, (result.stdout + result.stderr)[-4000:]
    scripted = json.loads((out / "scripted" / "meta" / "bcrl.json").read_text())
    assert scripted["record_config"]["seed"] == 100_000 and scripted["expert"] == "scripted"
    [operator] = scripted["demonstrators"]  # one slow operator without noise
    assert operator["speed"] == 0.7 and operator["noise_std"] == 0.0
    expert = out / "bc" / "checkpoints" / "last" / "pretrained_model"
    assert json.loads((expert / "config.json").read_text())["type"] == "bcrl"

    data = tmp_path / "demos"
    record = [str(ROOT / ".venv" / "bin" / "bcrl-record"), "--config_path=configs/record_weak_expert.yaml",
              f"--expert={expert}", f"--root={data}", "--n_episodes=1", "--episode_length=20", "--sigma=0.01"]
    result = subprocess.run(record, cwd=ROOT, env=env, capture_output=True, text=True)
    assert result.returncode == 0, (result.stdout + result.stderr)[-4000:]
    recorded = json.loads((data / "meta" / "bcrl.json").read_text())
    assert recorded["expert"] == str(expert) and recorded["record_config"]["sigma"] == 0.01
    assert recorded["record_config"]["images"] is False and recorded["record_config"]["miss_probability"] == 0.0
