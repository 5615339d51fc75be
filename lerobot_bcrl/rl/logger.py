"""bcrl-finetune's logs: one row per PPO iteration to `logs.csv` (and TensorBoard, wandb when asked), and the
summary of a batch of finished episodes that training rows and evaluations share.
"""

from __future__ import annotations

import csv

import draccus
import numpy as np

from lerobot_bcrl.rl.rollout import EpisodeStats
from lerobot_bcrl.stats import mean_ci95

# Seconds per iteration, and what each measures (bcrl-report's "where the time goes" table).
TIME_COLUMNS = {
    "collect_s": "collect (wall)", "learn_s": "learn (wall)",
    "simulation_s": "simulation (workers' wall time, summed)", "rendering_s": "rendering (workers' wall time, summed)",
    "policy_s": "policy and bookkeeping in the workers (wall time, summed)",
    "learner_data_s": "learner: minibatches and demo batches",
    "bc_term_s": "learner: BC forward and gradient-share norms", "update_s": "learner: PPO forward/backward, step",
}
LOG_COLUMNS = [
    "env_steps", "ppo_iteration", "optim_step", "theta", "wall_s", "worker_restarts", *TIME_COLUMNS,
    "train_return", "train_success", "train_episodes",
    "loss", "policy_loss", "value_loss", "entropy", "continuous_entropy", "gripper_entropy",
    "approx_kl", "clipfrac", "explained_variance",
    "optim_steps_taken", "kl_stopped",
    "grad_norm", "bc_term_grad_norm", "ppo_term_grad_norm", "bc_grad_share", "bc_scale",
    "bc_loss", "bc_l1", "bc_l2", "bc_cosine", "bc_gripper_ce", "bc_rot_l1", "bc_rot_l2",
    "bc_aux_eef_mse", "bc_aux_grasp_mse", "gripper_accuracy",
    "eval_return", "eval_return_ci95", "eval_success", "eval_steps_to_lift", "eval_episodes",
]


def summarize_episodes(episodes: list[EpisodeStats], prefix: str) -> dict[str, float]:
    """Mean return (with its 95 % interval), success rate and steps to lift; {} when no episode ended."""
    if not episodes:
        return {}
    mean_return, ci95 = mean_ci95(e.episode_return for e in episodes)
    lifts = [e.steps_to_lift for e in episodes if e.steps_to_lift is not None]
    return {
        f"{prefix}_return": mean_return,
        f"{prefix}_return_ci95": ci95,
        f"{prefix}_success": float(np.mean([e.success for e in episodes])),
        f"{prefix}_steps_to_lift": float(np.mean(lifts)) if lifts else float("nan"),
        f"{prefix}_episodes": len(episodes),
    }


class RunLogger:
    """CSV (always), TensorBoard (if installed and asked), wandb (only when asked)."""

    def __init__(self, cfg, resume_env_steps: int | None):
        self.csv_path = cfg.output_dir / "logs.csv"
        if resume_env_steps is not None and self.csv_path.exists():  # drop rows the killed run logged after its checkpoint
            rows = [r for r in csv.DictReader(self.csv_path.open()) if int(r["env_steps"]) <= resume_env_steps]
            self._write_rows(rows)
        elif not self.csv_path.exists() or resume_env_steps is None:
            self._write_rows([])
        self.tensorboard = self.wandb = None
        if cfg.tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self.tensorboard = SummaryWriter(str(cfg.output_dir / "tensorboard"))
            except ImportError:
                pass
        if cfg.wandb:
            import wandb

            self.wandb = wandb.init(project="lerobot-bcrl", name=cfg.output_dir.name, config=draccus.encode(cfg))

    def _write_rows(self, rows: list[dict]) -> None:
        with self.csv_path.open("w", newline="") as f:
            writer = csv.DictWriter(f, LOG_COLUMNS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)

    def log(self, row: dict) -> None:
        with self.csv_path.open("a", newline="") as f:
            csv.DictWriter(f, LOG_COLUMNS, extrasaction="ignore").writerow(row)
        numeric = {k: v for k, v in row.items() if isinstance(v, (int, float)) and k != "env_steps"}
        if self.tensorboard:
            for name, value in numeric.items():
                self.tensorboard.add_scalar(name, value, row["env_steps"])
        if self.wandb:
            self.wandb.log(numeric, step=row["env_steps"])

    def close(self) -> None:
        if self.tensorboard:
            self.tensorboard.close()
        if self.wandb:
            self.wandb.finish()
