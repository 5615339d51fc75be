"""`bcrl-eval-offline`: a policy's actions against held-out demonstrations, frame by frame (paper Figs. 4, 5).

Example:
    bcrl-eval-offline --policy.path=outputs/train/bc/checkpoints/last/pretrained_model \
        --dataset.root=data/lift_sigma0.1 --episodes='[45,46,47,48,49]'
Writes `offline_metrics.json` (per-step and averaged: delta-position direction error in degrees, rotation
error in radians, gripper accuracy) and `offline_metrics.png` into --output_dir.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import draccus
import numpy as np
import torch
from tqdm import tqdm

# Frames whose demonstrated delta_pos is shorter than this have no meaningful direction.
MIN_DIRECTION_NORM_M = 1e-4


@dataclass
class PolicyPathConfig:
    path: Path | None = None  # a `pretrained_model` folder written by lerobot-train


@dataclass
class DatasetPathConfig:
    repo_id: str = "local/bcrl_lift"
    root: Path | None = None  # default $HF_LEROBOT_HOME/<repo_id>


@dataclass
class EvalOfflineConfig:
    policy: PolicyPathConfig = field(default_factory=PolicyPathConfig)
    dataset: DatasetPathConfig = field(default_factory=DatasetPathConfig)
    episodes: list[int] | None = None  # held-out episode indices; None: every episode
    output_dir: Path | None = None  # default outputs/eval_offline/<date>_<time>
    batch_size: int = 256
    device: str = "cpu"


def action_errors(pred_action: np.ndarray, target_action: np.ndarray) -> dict[str, np.ndarray]:
    """Per-frame errors of 8-D actions: direction (deg, NaN where the target barely moves), rotation, gripper."""
    pred_pos, target_pos = pred_action[:, :3], target_action[:, :3]
    pred_norm = np.linalg.norm(pred_pos, axis=1)
    target_norm = np.linalg.norm(target_pos, axis=1)
    cosine = np.sum(pred_pos * target_pos, axis=1) / np.maximum(pred_norm * target_norm, 1e-12)
    direction_deg = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    direction_deg[target_norm < MIN_DIRECTION_NORM_M] = np.nan
    # The angle of q_hat^-1 q is 2 acos|q_hat . q| for unit quaternions, whichever cover either is on.
    quat_dot = np.abs(np.sum(pred_action[:, 3:7] * target_action[:, 3:7], axis=1))
    rotation_rad = 2.0 * np.arccos(np.clip(quat_dot, 0.0, 1.0))
    gripper_correct = (np.sign(pred_action[:, 7]) == np.sign(target_action[:, 7])).astype(np.float64)
    return {"direction_error_deg": direction_deg, "rotation_error_rad": rotation_rad, "gripper_accuracy": gripper_correct}


def per_step_means(values: np.ndarray, frame_index: np.ndarray) -> list[float | None]:
    """Mean over episodes at each frame index (None where every value is NaN)."""
    means = []
    for step in range(int(frame_index.max()) + 1):
        at_step = values[(frame_index == step) & ~np.isnan(values)]
        means.append(float(at_step.mean()) if at_step.size else None)
    return means


def predict_dataset(cfg: EvalOfflineConfig) -> dict[str, np.ndarray]:
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    import lerobot_bcrl  # noqa: F401  (registers the `bcrl` policy type)

    policy_config = PreTrainedConfig.from_pretrained(cfg.policy.path)
    policy_config.device = cfg.device
    policy = get_policy_class(policy_config.type).from_pretrained(cfg.policy.path, config=policy_config)
    policy.eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy_config,
        pretrained_path=str(cfg.policy.path),
        preprocessor_overrides={"device_processor": {"device": cfg.device}},
    )
    dataset = LeRobotDataset(cfg.dataset.repo_id, root=cfg.dataset.root, episodes=cfg.episodes)
    loader = torch.utils.data.DataLoader(dataset, batch_size=cfg.batch_size, shuffle=False)
    columns: dict[str, list[np.ndarray]] = {"pred": [], "target": [], "frame_index": [], "episode_index": []}
    for batch in tqdm(loader, desc="predicting held-out frames", unit="batch"):
        target = batch["action"].numpy()
        with torch.no_grad():
            pred = postprocessor(policy.select_action(preprocessor(batch)))
        columns["pred"].append(pred.cpu().numpy())
        columns["target"].append(target)
        columns["frame_index"].append(batch["frame_index"].numpy())
        columns["episode_index"].append(batch["episode_index"].numpy())
    return {key: np.concatenate(values) for key, values in columns.items()}


def summarize(predictions: dict[str, np.ndarray]) -> dict:
    errors = action_errors(predictions["pred"], predictions["target"])
    summary: dict = {"n_frames": int(len(predictions["pred"]))}
    summary["episodes"] = sorted(int(e) for e in np.unique(predictions["episode_index"]))
    summary["mean"] = {name: float(np.nanmean(values)) for name, values in errors.items()}
    summary["per_step"] = {name: per_step_means(values, predictions["frame_index"]) for name, values in errors.items()}
    summary["per_episode"] = {
        int(episode): {
            name: float(np.nanmean(values[predictions["episode_index"] == episode])) for name, values in errors.items()
        }
        for episode in summary["episodes"]
    }
    return summary


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {
        "direction_error_deg": "delta-position direction error (deg)",
        "rotation_error_rad": "rotation error (rad)",
        "gripper_accuracy": "gripper accuracy",
    }
    fig, axes = plt.subplots(len(labels), 1, figsize=(8, 8), sharex=True)
    for ax, (name, label) in zip(axes, labels.items(), strict=True):
        values = np.array([np.nan if v is None else v for v in summary["per_step"][name]])
        ax.plot(np.arange(len(values)), values)
        ax.axhline(summary["mean"][name], linestyle="--", color="grey", label=f"mean {summary['mean'][name]:.3g}")
        ax.set_ylabel(label, fontsize=8)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("step in episode (mean over held-out episodes)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def eval_offline(cfg: EvalOfflineConfig) -> Path:
    if cfg.policy.path is None:
        raise ValueError("--policy.path is required")
    output_dir = cfg.output_dir or Path("outputs/eval_offline") / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    output_dir.mkdir(parents=True, exist_ok=True)
    summary = summarize(predict_dataset(cfg))
    summary["policy_path"] = str(cfg.policy.path)
    summary["dataset_root"] = str(cfg.dataset.root)
    (output_dir / "offline_metrics.json").write_text(json.dumps(summary, indent=2) + "\n")
    plot(summary, output_dir / "offline_metrics.png")
    return output_dir


def main() -> None:
    logging.basicConfig(level=logging.INFO)
    cfg = draccus.parse(EvalOfflineConfig)
    output_dir = eval_offline(cfg)
    mean = json.loads((output_dir / "offline_metrics.json").read_text())["mean"]
    print(
        f"held-out frames: direction error {mean['direction_error_deg']:.1f} deg, "
        f"rotation error {mean['rotation_error_rad']:.4f} rad, gripper accuracy {mean['gripper_accuracy']:.3f}"
    )
    print(f"wrote {output_dir / 'offline_metrics.json'} and {output_dir / 'offline_metrics.png'}")


if __name__ == "__main__":
    main()
