"""The `bcrl` policy through the unmodified LeRobot CLIs (lerobot-train, resume, lerobot-eval) and bcrl-eval-offline.

Tiny budgets: a few training steps and one short episode each; the plugin is found by its distribution name.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from policy_fixtures import image_dataset_root, lowdim_dataset_root  # noqa: F401

BIN = Path(sys.executable).parent


def run_cli(name: str, *args: str, timeout: int = 120) -> str:
    result = subprocess.run(
        [str(BIN / name), *args], capture_output=True, text=True, timeout=timeout, env=os.environ.copy()
    )
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-4000:]
    return output


def train_args(dataset_root: Path, output_dir: Path, steps: int) -> list[str]:
    return [
        "--policy.type=bcrl",
        f"--dataset.repo_id=local/{dataset_root.name}",
        f"--dataset.root={dataset_root}",
        "--policy.push_to_hub=false",
        f"--steps={steps}",
        "--batch_size=8",
        f"--output_dir={output_dir}",
        "--num_workers=0",
        "--policy.device=cpu",
        "--log_freq=1",
        "--save_freq=2",
    ]


def eval_args(checkpoint: Path, output_dir: Path, *extra: str) -> list[str]:
    return [
        f"--policy.path={checkpoint}",
        "--env.type=bcrl_lift",
        "--env.episode_length=8",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        "--eval.use_async_envs=false",
        "--policy.device=cpu",
        f"--output_dir={output_dir}",
        *extra,
    ]


@pytest.fixture(scope="module")
def lowdim_run(lowdim_dataset_root, tmp_path_factory) -> Path:
    output_dir = tmp_path_factory.mktemp("train") / "lowdim"
    output = run_cli("lerobot-train", *train_args(lowdim_dataset_root, output_dir, steps=2))
    assert "bc_aux_grasp_mse" in output  # the aux targets reached forward under lerobot-train
    return output_dir


@pytest.mark.slow
def test_lerobot_train_writes_checkpoints_and_resumes(lowdim_run):
    pretrained = lowdim_run / "checkpoints" / "last" / "pretrained_model"
    for name in ("config.json", "model.safetensors", "train_config.json", "policy_preprocessor.json"):
        assert (pretrained / name).exists(), name
    assert json.loads((pretrained / "config.json").read_text())["type"] == "bcrl"

    output = run_cli(
        "lerobot-train", "--resume=true", f"--config_path={pretrained / 'train_config.json'}", "--steps=4"
    )
    assert "step:4 " in output and "bc_aux_eef_mse" in output
    step_file = lowdim_run / "checkpoints" / "last" / "training_state" / "training_step.json"
    assert json.loads(step_file.read_text())["step"] == 4


@pytest.mark.slow
def test_lerobot_eval_rolls_out_a_lowdim_checkpoint(lowdim_run, tmp_path):
    checkpoint = lowdim_run / "checkpoints" / "000002" / "pretrained_model"
    run_cli("lerobot-eval", *eval_args(checkpoint, tmp_path / "eval", "--env.obs_type=agent_pos"))
    info = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1
    assert "pc_success" in info["overall"] and "avg_sum_reward" in info["overall"]


@pytest.mark.slow
def test_lerobot_train_and_eval_with_images(image_dataset_root, tmp_path):
    run_cli("lerobot-train", *train_args(image_dataset_root, tmp_path / "train", steps=2))
    checkpoint = tmp_path / "train" / "checkpoints" / "last" / "pretrained_model"
    assert json.loads((checkpoint / "config.json").read_text())["input_features"]["observation.images.agentview"]
    run_cli("lerobot-eval", *eval_args(checkpoint, tmp_path / "eval"))
    info = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1


@pytest.mark.slow
def test_bcrl_eval_offline_writes_metrics_and_plot(lowdim_run, lowdim_dataset_root, tmp_path):
    checkpoint = lowdim_run / "checkpoints" / "000002" / "pretrained_model"
    run_cli(
        "bcrl-eval-offline",
        f"--policy.path={checkpoint}",
        f"--dataset.repo_id=local/{lowdim_dataset_root.name}",
        f"--dataset.root={lowdim_dataset_root}",
        "--episodes=[1]",
        f"--output_dir={tmp_path}",
    )
    summary = json.loads((tmp_path / "offline_metrics.json").read_text())
    assert summary["episodes"] == [1] and summary["n_frames"] == 50
    assert 0.0 <= summary["mean"]["gripper_accuracy"] <= 1.0
    assert 0.0 <= summary["mean"]["direction_error_deg"] <= 180.0
    assert len(summary["per_step"]["rotation_error_rad"]) == 50
    assert (tmp_path / "offline_metrics.png").stat().st_size > 1000
