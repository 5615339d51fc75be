"""BC+RL: PPO fine-tuning of a `bcrl` policy with a decaying BC term, `L = theta_t * L_BC + (1 - theta_t) * L_PPO`.

One module, CleanRL-style: collect a rollout, GAE, epochs over minibatches (each with a demo minibatch for
the BC term), log, evaluate, checkpoint in LeRobot's layout. The CLI is `bcrl-finetune`.
"""


import csv
import json
import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path

import draccus
import numpy as np
import torch
from lerobot.configs import parser
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.configs import EnvConfig
from torch import Tensor
from tqdm import tqdm

from lerobot_bcrl.envs.configuration_lift import LiftEnvConfig
from lerobot_bcrl.stats import mean_ci95
from lerobot_bcrl.rl.agent import Agent, BCRLAgent
from lerobot_bcrl.rl.normalization import OBS_NORMALIZATION_MODES, RewardScaler, RunningObservationStats, find_normalizer
from lerobot_bcrl.rl.rollout import EpisodeStats, RolloutWorkers, Trajectories, make_gym_env, make_workers
from lerobot_bcrl.rl.schedule import ScheduleConfig, ScheduleState

EVAL_SEED_OFFSET = 1_000_000  # the final evaluation's (test) seeds: no dataset or training rollout draws them
VALIDATION_SEED_OFFSET = 2_000_000  # the periodic evaluations' seeds, which may choose the result: never the test's
SELECTIONS = ("last", "best_validation")
FINETUNE_CONFIG_NAME = "finetune_config.json"
ROLLOUT_POLICY_DIR = "rollout_policy"  # what the workers load once (config, processors); weights come per rollout


# ------------------------------------------------------------------------------------------------ config
@dataclass
class DemoDatasetConfig:
    repo_id: str = "local/lift"  # the demonstrations of the BC term (and the feature shapes/stats from scratch)
    root: str | None = None
    episodes: list[int] | None = None  # None: all episodes
    video_backend: str | None = None


@dataclass
class PPOConfig:
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2  # clipped surrogate's epsilon
    c1: float = 1.0  # weight of the clipped surrogate in L_PPO (method.md section 4)
    c2: float = 0.5  # weight of the value loss in L_PPO
    entropy_coef: float = 0.0
    update_epochs: int = 4
    minibatch_size: int = 256
    learning_rate: float = 1e-4
    max_grad_norm: float = 0.5
    normalize_advantages: bool = True
    # Rewards divided by a running std of the discounted return (CleanRL's NormalizeReward).
    normalize_rewards: bool = True
    # Observations are normalised by the policy's preprocessor. "dataset": with the demonstrations' mean/std
    # (what BC trained with; fixed). "running": the mean/std of the state features start there (weighted as
    # the dataset's frame count) and follow every rollout (CleanRL's NormalizeObservation); checkpoints carry
    # them, so lerobot-eval normalises as training did. No normalisation: --policy.normalization_mapping.
    obs_normalization: str = "dataset"
    target_kl: float | None = None  # stop an iteration's epochs early when approx_kl exceeds it
    # CleanRL's anneal_lr: the learning rate falls linearly from learning_rate (at env step 0) towards 0 (at
    # total_env_steps), set before each iteration from the env step count, so a resumed run goes on where it was
    # (resuming with a larger --total_env_steps raises it again).
    anneal_lr: bool = False
    # Set the policy's learned log-std at the start (BC never trains it), for delta_pos / scale and for the
    # quaternion: the demos barely rotate, and quaternion noise of the position's size turns the wrist
    # ~15 degrees a step (clamped to pi/40), which the BC policy never saw.
    reset_log_std: float | None = -2.0
    reset_log_std_rotation: float | None = -5.0
    # Anneal the exploration std of delta_pos: before each iteration the position log-std is set on the line from
    # reset_log_std (at env step anneal_log_std_from) to anneal_log_std_to (at total_env_steps), and the log-std
    # (rotation's too, which keeps its value) is then a schedule, not learned. None: learned from reset_log_std.
    anneal_log_std_to: float | None = None
    anneal_log_std_from: int = 0
    # True: `theta * L_BC + (1 - theta) * c1 * L_CLIP + c2 * L_VF`, the critic trained from the first update
    # (during alpha too). False: the paper's `theta * L_BC + (1 - theta) * (c1 * L_CLIP + c2 * L_VF)`, in
    # which the value head gets no gradient while theta = 1 and PPO starts on an untrained critic.
    value_loss_always: bool = True
    # How theta_t weighs the two terms. "loss": the paper's `theta * L_BC + (1 - theta) * L_PPO`. "gradient_share":
    # L_BC is rescaled per minibatch by ||grad L_PPO|| / ||grad L_BC|| (policy term, detached), so theta_t is the BC
    # term's share of the policy gradient and the update keeps PPO's gradient scale (PPO's policy gradient is
    # 2-9x the BC loss's on our Lift checkpoints: with "loss", theta_t 0.42 gave BC 8 % of the update).
    term_weighting: str = "loss"
    # The value's own MLP (hidden widths), set on the policy as it loads, so that a config file can hold it
    # although `--policy.path` takes the policy's config from the checkpoint: a BC checkpoint gets a freshly
    # initialised critic (BCRLConfig.critic_hidden_dims). None keeps the policy's; a policy that already has
    # another critic is an error.
    critic_hidden_dims: tuple[int, ...] | None = None

    def __post_init__(self):
        if self.term_weighting not in ("loss", "gradient_share"):
            raise ValueError(f"ppo.term_weighting must be 'loss' or 'gradient_share', got {self.term_weighting!r}")
        if self.anneal_log_std_to is not None and self.reset_log_std is None:
            raise ValueError("ppo.anneal_log_std_to needs ppo.reset_log_std, the log-std the annealing starts from")


@dataclass
class RolloutConfig:
    n_workers: int = 2  # subprocesses; 0 runs the envs in this process
    envs_per_worker: int = 2
    steps_per_env: int = 128  # rollout length per env per iteration

    @property
    def n_envs(self) -> int:
        return max(self.n_workers, 1) * self.envs_per_worker

    @property
    def steps_per_iteration(self) -> int:  # env steps one PPO iteration collects; a run ends on a whole iteration
        return self.n_envs * self.steps_per_env


@dataclass
class FinetuneConfig:
    dataset: DemoDatasetConfig = field(default_factory=DemoDatasetConfig)
    env: EnvConfig = field(default_factory=lambda: LiftEnvConfig(obs_type="agent_pos"))
    # `--policy.path=<BC pretrained_model>` fine-tunes a checkpoint; `--policy.type=bcrl` starts from scratch.
    policy: PreTrainedConfig | None = None
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)
    total_env_steps: int = 300_000  # 0: no training, only the final evaluation (the "BC only" baseline)
    bc_batch_size: int = 256  # demo minibatch size for the BC term
    output_dir: Path | None = None
    resume: bool = False
    seed: int = 1000
    label: str | None = None  # method name in the report; default: BC / BC+RL / PPO from scratch
    eval_freq: int = 50_000  # env steps between periodic evaluations, on validation seeds (0: only the final one)
    eval_episodes: int = 10
    # The run's result (the final evaluation on the test seeds, `checkpoints/best`): "last", or "best_validation":
    # the policy of the periodic evaluation with the highest success rate, then return (the earliest of equals),
    # the starting policy included (evaluated before the first update), like robomimic's best-rollout checkpoints.
    select: str = "last"
    final_eval_episodes: int = 50
    # Also run the final evaluation with actions sampled as in training (the stochastic policy PPO optimises;
    # the deterministic evaluation above is what lerobot-eval runs); reported as `eval_sampled_*`.
    final_eval_sampled: bool = False
    save_freq: int = 50_000  # env steps between checkpoints (and one at the end)
    # Log every evaluation episode to <output_dir>/eval_rrd/*.rrd: what happened, the policy's predicted
    # actions and values, and theta_t and the env step count at that evaluation (open with `rerun`).
    eval_rerun: bool = False
    tensorboard: bool = True  # also log to <output_dir>/tensorboard if tensorboard is installed
    wandb: bool = False

    def __post_init__(self):
        policy_path = parser.get_path_arg("policy")
        if policy_path:  # like lerobot-train: the checkpoint's config, with --policy.* overrides on top
            self.policy = PreTrainedConfig.from_pretrained(policy_path, cli_overrides=parser.get_cli_overrides("policy"))
            self.policy.pretrained_path = Path(policy_path)
        if self.output_dir is None:
            self.output_dir = Path("outputs/finetune") / time.strftime("%Y-%m-%d_%H-%M-%S")
        self.output_dir = Path(self.output_dir)

    @classmethod
    def __get_path_fields__(cls) -> list[str]:
        return ["policy"]

    @property
    def method(self) -> str:
        if self.label:
            return self.label
        if self.total_env_steps == 0:  # an evaluation: of a BC checkpoint, or of one fine-tuned by bcrl-finetune
            return "BC+RL" if self.policy.pretrained_path and policy_env_steps(self.policy.pretrained_path) else "BC"
        if not self.policy.pretrained_path:
            return "PPO from scratch"
        floor = self.schedule.floor
        return f"BC+RL, theta_t >= {floor:g}" if floor > 0 else "BC+RL"


# --------------------------------------------------------------------------------------- maths of PPO
def compute_gae(rewards: Tensor, values: Tensor, dones: Tensor, last_values: Tensor, gamma: float,
                gae_lambda: float) -> tuple[Tensor, Tensor]:
    """Advantages and returns (T, N) by generalised advantage estimation; `dones[t]` ends the episode after t."""
    advantages = torch.zeros_like(rewards)
    next_advantage = torch.zeros_like(last_values)
    next_values = last_values
    for t in reversed(range(rewards.shape[0])):
        not_done = 1.0 - dones[t]
        delta = rewards[t] + gamma * next_values * not_done - values[t]
        next_advantage = delta + gamma * gae_lambda * not_done * next_advantage
        advantages[t] = next_advantage
        next_values = values[t]
    return advantages, advantages + values


def ppo_loss_terms(new_log_prob: Tensor, old_log_prob: Tensor, advantages: Tensor, new_value: Tensor,
                   returns: Tensor, clip_eps: float) -> dict[str, Tensor]:
    """Clipped surrogate (as a loss), value MSE, and the diagnostics CleanRL logs."""
    log_ratio = new_log_prob - old_log_prob
    ratio = log_ratio.exp()
    surrogate = advantages * ratio
    clipped_surrogate = advantages * ratio.clamp(1 - clip_eps, 1 + clip_eps)
    with torch.no_grad():
        approx_kl = ((ratio - 1) - log_ratio).mean()  # the low-variance estimator (Schulman's k3)
        clipfrac = ((ratio - 1).abs() > clip_eps).float().mean()
    return {
        "policy_loss": -torch.min(surrogate, clipped_surrogate).mean(),
        "value_loss": 0.5 * (new_value - returns).pow(2).mean(),
        "approx_kl": approx_kl,
        "clipfrac": clipfrac,
    }


def explained_variance(predicted: np.ndarray, target: np.ndarray) -> float:
    target_var = np.var(target)
    return float("nan") if target_var == 0 else float(1 - np.var(target - predicted) / target_var)


def flat_gradient(module: torch.nn.Module, term: Tensor) -> Tensor:
    """d term / d parameters as one vector (zeros where unused), without touching `.grad` (the graph is kept)."""
    params = [p for p in module.parameters() if p.requires_grad]
    if not term.requires_grad:
        return torch.zeros(sum(p.numel() for p in params))
    grads = torch.autograd.grad(term, params, retain_graph=True, allow_unused=True)
    return torch.cat([(torch.zeros_like(p) if g is None else g.detach()).reshape(-1) for p, g in zip(params, grads)])


def gradient_norm(module: torch.nn.Module, term: Tensor) -> float:
    return float(flat_gradient(module, term).norm())


def term_gradient_norms(module: torch.nn.Module, bc_term: Tensor, ppo_term: Tensor) -> dict[str, float]:
    """Norms of the gradients of the weighted BC term and of the weighted PPO policy term (value loss left out),
    and the BC term's share of their sum: how much theta_t weighs once each term's gradient scale counts."""
    bc_norm, ppo_norm = gradient_norm(module, bc_term), gradient_norm(module, ppo_term)
    share = bc_norm / (bc_norm + ppo_norm) if bc_norm + ppo_norm > 0 else float("nan")
    return {"bc_term_grad_norm": bc_norm, "ppo_term_grad_norm": ppo_norm, "bc_grad_share": share}


def bc_gradient_scale(module: torch.nn.Module, bc_loss: Tensor, ppo_loss: Tensor) -> float:
    """`||grad L_PPO|| / ||grad L_BC||`: the factor that gives L_BC the PPO policy term's gradient scale (1 when
    either gradient is zero)."""
    bc_norm, ppo_norm = gradient_norm(module, bc_loss), gradient_norm(module, ppo_loss)
    return ppo_norm / bc_norm if bc_norm > 0 and ppo_norm > 0 else 1.0


def ppo_losses(agent: Agent, minibatch: dict, cfg: PPOConfig) -> tuple[dict[str, Tensor], Tensor, Tensor, Tensor]:
    """PPO's terms on one minibatch: `ppo_loss_terms`, the entropy, the weighted policy term
    `c1 * L_CLIP - entropy_coef * H` and the weighted value loss `c2 * L_VF`."""
    new_log_prob, entropy, new_value = agent.evaluate(minibatch["obs"], minibatch["actions"])
    advantages = minibatch["advantages"]
    if cfg.normalize_advantages and advantages.numel() > 1:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    ppo = ppo_loss_terms(new_log_prob, minibatch["log_probs"], advantages, new_value, minibatch["returns"], cfg.clip_eps)
    return ppo, entropy, cfg.c1 * ppo["policy_loss"] - cfg.entropy_coef * entropy.mean(), cfg.c2 * ppo["value_loss"]


def bcrl_loss(agent: Agent, minibatch: dict, demo_batch: dict | None, theta: float, cfg: PPOConfig,
              bc_forward=None, measure_gradients: bool = False) -> tuple[Tensor, dict[str, float]]:
    """`theta * L_BC + (1 - theta) * L_PPO` on one PPO minibatch and one preprocessed demo minibatch; with
    `measure_gradients`, also `term_gradient_norms` (two more backward passes). With
    `cfg.term_weighting == "gradient_share"`, L_BC is first rescaled by `bc_gradient_scale` (two more)."""
    ppo, entropy, ppo_loss, value_loss = ppo_losses(agent, minibatch, cfg)
    # No demo forward pass when the BC term has no weight (pure PPO, or after phi).
    bc_loss, bc_metrics = bc_forward(demo_batch) if theta > 0 else (torch.zeros(()), {})
    gradient_metrics = {}
    if cfg.term_weighting == "gradient_share" and theta > 0:
        bc_scale = bc_gradient_scale(agent.module, bc_loss, ppo_loss)
        bc_loss, gradient_metrics["bc_scale"] = bc_scale * bc_loss, bc_scale
    if measure_gradients:
        gradient_metrics.update(term_gradient_norms(agent.module, theta * bc_loss, (1 - theta) * ppo_loss))

    if cfg.value_loss_always:
        loss = theta * bc_loss + (1 - theta) * ppo_loss + value_loss
    else:
        ppo_loss = ppo_loss + value_loss
        loss = theta * bc_loss + (1 - theta) * ppo_loss

    metrics = {name: float(value.detach()) for name, value in ppo.items()}
    metrics.update(bc_metrics, **gradient_metrics, entropy=float(entropy.mean().detach()),
                   ppo_loss=float(ppo_loss.detach()), loss=float(loss.detach()))
    return loss, metrics


# ----------------------------------------------------------------------------------- the update loop
def learning_rate_at(cfg: PPOConfig, env_steps: int, total_env_steps: int) -> float:
    """The learning rate of the iteration that starts after `env_steps` env steps."""
    if not cfg.anneal_lr:
        return cfg.learning_rate
    return cfg.learning_rate * max(1.0 - env_steps / total_env_steps, 0.0)


def position_log_std_at(cfg: PPOConfig, env_steps: int, total_env_steps: int) -> float | None:
    """The position log-std of the iteration that starts after `env_steps` env steps (None: not annealed)."""
    if cfg.anneal_log_std_to is None:
        return None
    span = total_env_steps - cfg.anneal_log_std_from
    progress = 1.0 if span <= 0 else min(max((env_steps - cfg.anneal_log_std_from) / span, 0.0), 1.0)
    return cfg.reset_log_std + (cfg.anneal_log_std_to - cfg.reset_log_std) * progress


def low_dim_observations(trajectories: Trajectories) -> dict[str, np.ndarray]:
    """The rollout's non-image observations, (T*N, ...) per raw env key."""
    return {key: value.reshape(-1, *value.shape[2:]) for key, value in trajectories.observations.items()
            if not key.startswith("pixels")}


def flatten_time_and_envs(trajectories: Trajectories, advantages: Tensor, returns: Tensor) -> dict:
    flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731  (T, N, ...) -> (T*N, ...)
    return {
        "obs": {key: flat(value) for key, value in trajectories.observations.items()},
        "actions": flat(torch.as_tensor(trajectories.actions)),
        "log_probs": flat(torch.as_tensor(trajectories.log_probs)),
        "values": flat(torch.as_tensor(trajectories.values)),
        "advantages": flat(advantages),
        "returns": flat(returns),
    }


def training_batch(trajectories: Trajectories, rewards: np.ndarray, cfg: PPOConfig) -> dict:
    """GAE advantages and returns (time-limit truncations bootstrapped from their value), flattened to samples."""
    values = torch.as_tensor(trajectories.values)
    bootstrapped_rewards = torch.as_tensor(rewards) + cfg.gamma * torch.as_tensor(trajectories.truncation_values)
    advantages, returns = compute_gae(bootstrapped_rewards, values, torch.as_tensor(trajectories.dones),
                                      torch.as_tensor(trajectories.last_values), cfg.gamma, cfg.gae_lambda)
    return flatten_time_and_envs(trajectories, advantages, returns)


def select_minibatch(agent: Agent, batch: dict, index: Tensor) -> dict:
    """Rows `index` of a training batch, observations through the agent's preprocessing."""
    minibatch = {key: value[index] for key, value in batch.items() if key != "obs"}
    minibatch["obs"] = agent.observation_batch({k: v[index.numpy()] for k, v in batch["obs"].items()})
    return minibatch


def ppo_update(agent: Agent, optimizer: torch.optim.Optimizer, trajectories: Trajectories, rewards: np.ndarray,
               cfg: PPOConfig, schedule_cfg: ScheduleConfig, schedule_state: ScheduleState,
               demo_batches=None, bc_forward=None) -> dict[str, float]:
    """One PPO iteration: GAE, then `update_epochs` passes over shuffled minibatches; returns mean metrics."""
    batch = training_batch(trajectories, rewards, cfg)
    batch_size = batch["actions"].shape[0]

    agent.module.train()
    history: dict[str, list[float]] = {}
    for epoch in range(cfg.update_epochs):
        permutation = torch.randperm(batch_size)
        for start in range(0, batch_size, cfg.minibatch_size):
            index = permutation[start : start + cfg.minibatch_size]
            minibatch = select_minibatch(agent, batch, index)
            theta = schedule_state.theta(schedule_cfg)
            demo_batch = next(demo_batches) if (theta > 0 and demo_batches is not None) else None

            loss, metrics = bcrl_loss(agent, minibatch, demo_batch, theta, cfg, bc_forward,
                                      measure_gradients=epoch == 0 and start == 0)  # once per iteration

            optimizer.zero_grad()
            loss.backward()
            metrics["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(agent.module.parameters(), cfg.max_grad_norm))
            optimizer.step()
            schedule_state.optim_step += 1
            metrics["theta"] = theta
            for name, value in metrics.items():
                history.setdefault(name, []).append(value)
        if cfg.target_kl is not None and np.mean(history["approx_kl"][-(batch_size // cfg.minibatch_size):]) > cfg.target_kl:
            break
    schedule_state.ppo_iteration += 1
    summary = {name: float(np.mean(values_)) for name, values_ in history.items()}
    summary["explained_variance"] = explained_variance(batch["values"].numpy(), batch["returns"].numpy())
    return summary


# ------------------------------------------------------------------------------------- checkpoints
TRAINING_STEP_FILE = "training_step.json"


def checkpoint_name(env_steps: int) -> str:
    return f"{env_steps:09d}"


def point_symlink(checkpoints_dir: Path, name: str, checkpoint_dir: Path) -> None:
    """`checkpoints/<name>` -> `<step>`, replaced atomically."""
    tmp_link = checkpoints_dir / f".{name}_tmp"
    tmp_link.unlink(missing_ok=True)
    tmp_link.symlink_to(checkpoint_dir.name)
    os.replace(tmp_link, checkpoints_dir / name)


def save_checkpoint(cfg: FinetuneConfig, env_steps: int, agent: BCRLAgent, postprocessor, optimizer,
                    schedule_state: ScheduleState, reward_scaler: RewardScaler | None,
                    obs_stats: RunningObservationStats | None = None, best: dict | None = None) -> Path:
    """LeRobot's layout (`checkpoints/<step>/{pretrained_model,training_state}`, `last` symlink), atomically.
    `best`: the validation evaluation that chose the result so far (`--select=best_validation`), kept for a resume."""
    from lerobot.optim.optimizers import save_optimizer_state
    from lerobot.utils.random_utils import save_rng_state

    checkpoints_dir = cfg.output_dir / "checkpoints"
    final_dir = checkpoints_dir / checkpoint_name(env_steps)
    tmp_dir = checkpoints_dir / f".tmp_{checkpoint_name(env_steps)}"
    shutil.rmtree(tmp_dir, ignore_errors=True)
    pretrained_dir, state_dir = tmp_dir / "pretrained_model", tmp_dir / "training_state"
    agent.policy.save_pretrained(pretrained_dir)
    agent.preprocessor.save_pretrained(pretrained_dir)
    postprocessor.save_pretrained(pretrained_dir)
    with open(pretrained_dir / FINETUNE_CONFIG_NAME, "w") as f, draccus.config_type("json"):
        draccus.dump(cfg, f, indent=2)
    state_dir.mkdir(parents=True)
    save_optimizer_state(optimizer, state_dir)
    save_rng_state(state_dir)
    training_step = {"env_steps": env_steps, **asdict(schedule_state), "theta": schedule_state.theta(cfg.schedule),
                     "reward_scaler": reward_scaler.state_dict() if reward_scaler else None,
                     "obs_stats": obs_stats.state_dict() if obs_stats else None, "best": best}
    (state_dir / TRAINING_STEP_FILE).write_text(json.dumps(training_step, indent=2))
    if final_dir.exists():
        shutil.rmtree(final_dir)
    os.replace(tmp_dir, final_dir)
    point_symlink(checkpoints_dir, "last", final_dir)
    return final_dir


def better_on_validation(candidate: dict, best: dict | None) -> bool:
    """Higher success rate, then higher return; on a tie the earlier policy stays."""
    return best is None or (candidate["success"], candidate["return"]) > (best["success"], best["return"])


def load_training_state(checkpoint_dir: Path, optimizer) -> dict:
    from lerobot.optim.optimizers import load_optimizer_state
    from lerobot.utils.random_utils import load_rng_state

    state_dir = checkpoint_dir / "training_state"
    load_optimizer_state(optimizer, state_dir)
    load_rng_state(state_dir)
    return json.loads((state_dir / TRAINING_STEP_FILE).read_text())


def policy_env_steps(pretrained_path: str | Path | None) -> int:
    """Env steps of fine-tuning behind a policy: those of the bcrl-finetune checkpoint it was saved in, else 0
    (a lerobot-train checkpoint's training state counts optimisation steps, not env steps)."""
    if pretrained_path is None:
        return 0
    step_file = Path(pretrained_path).parent / "training_state" / TRAINING_STEP_FILE
    if not step_file.exists():
        return 0
    return int(json.loads(step_file.read_text()).get("env_steps", 0))


# ------------------------------------------------------------------------------------------ logging
LOG_COLUMNS = [
    "env_steps", "ppo_iteration", "optim_step", "theta", "learning_rate", "position_log_std",
    "wall_s", "collect_s", "learn_s",
    "train_return", "train_success", "train_episodes",
    "loss", "ppo_loss", "policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac", "explained_variance",
    "grad_norm", "bc_term_grad_norm", "ppo_term_grad_norm", "bc_grad_share", "bc_scale",
    "bc_loss", "bc_l1", "bc_l2", "bc_cosine", "bc_gripper_ce", "bc_quat", "bc_quat_sign",
    "bc_aux_eef_mse", "bc_aux_grasp_mse", "gripper_accuracy",
    "eval_return", "eval_return_ci95", "eval_success", "eval_steps_to_lift", "eval_episodes",
]


class RunLogger:
    """CSV (always), TensorBoard (if installed and asked), wandb (only when asked)."""

    def __init__(self, cfg: FinetuneConfig, resume_env_steps: int | None):
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


def summarize_episodes(episodes: list[EpisodeStats], prefix: str) -> dict[str, float]:
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


# ------------------------------------------------------------------------------------------- set-up
class DemoBuffer:
    """The demonstrations in memory (read once; cameras kept as uint8), sampled as endless shuffled minibatches.

    LeRobotDataset decodes one frame per `__getitem__`; a BC minibatch beside every PPO minibatch would spend
    most of the update there. Batches are preprocessed like lerobot-train's (normalised, aux.* kept).
    """

    def __init__(self, dataset, batch_size: int, seed: int, preprocessor):
        loader = torch.utils.data.DataLoader(dataset, batch_size=256, shuffle=False, num_workers=0)
        chunks = list(tqdm(loader, desc="loading demonstrations", leave=False))
        self.frames = {key: self._compact(key, torch.cat([c[key] for c in chunks]))
                       for key, value in chunks[0].items() if isinstance(value, Tensor)}
        self.n_frames = len(next(iter(self.frames.values())))
        self.batch_size = min(batch_size, self.n_frames)
        self.generator = torch.Generator().manual_seed(seed)
        self.preprocessor = preprocessor

    @staticmethod
    def _compact(key: str, value: Tensor) -> Tensor:
        return (value * 255).round().to(torch.uint8) if key.startswith("observation.images.") else value

    def __iter__(self):
        return self

    def __next__(self) -> dict[str, Tensor]:
        index = torch.randint(self.n_frames, (self.batch_size,), generator=self.generator)
        batch = {key: value[index] for key, value in self.frames.items()}
        batch.update({key: value.float() / 255 for key, value in batch.items() if value.dtype == torch.uint8})
        return self.preprocessor(batch)


def build_policy(cfg: FinetuneConfig, dataset):
    """The policy and processors the way lerobot-train builds them (from a checkpoint or from scratch)."""
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    cfg.policy.device = "cpu"
    policy = make_policy(cfg.policy, ds_meta=dataset.meta)
    pretrained = str(cfg.policy.pretrained_path) if cfg.policy.pretrained_path else None
    processor_kwargs = {"dataset_stats": dataset.meta.stats} if pretrained is None else {
        "preprocessor_overrides": {"device_processor": {"device": "cpu"}}}
    preprocessor, postprocessor = make_pre_post_processors(cfg.policy, pretrained_path=pretrained, **processor_kwargs)
    return policy, preprocessor, postprocessor


def set_critic(policy_cfg: PreTrainedConfig, critic_hidden_dims: tuple[int, ...] | None) -> None:
    """`--ppo.critic_hidden_dims` onto the policy's config (the checkpoint's, or --policy.type's)."""
    if critic_hidden_dims is None:
        return
    wanted, current = tuple(critic_hidden_dims), tuple(policy_cfg.critic_hidden_dims)
    if current and current != wanted:
        where = f"the policy at {policy_cfg.pretrained_path}" if policy_cfg.pretrained_path else "--policy"
        raise ValueError(f"ppo.critic_hidden_dims={list(wanted)} but {where} has critic_hidden_dims={list(current)}: "
                         "drop one of them")
    policy_cfg.critic_hidden_dims = wanted


def env_gym_kwargs(cfg: FinetuneConfig, uses_images: bool) -> dict:
    kwargs = dict(cfg.env.gym_kwargs)
    if not uses_images:
        kwargs["obs_type"] = "agent_pos"  # a low-dim policy never needs the camera (3x faster)
    return kwargs


def worker_kwargs(cfg: FinetuneConfig, policy_dir: Path, gym_kwargs: dict, seed: int) -> list[dict]:
    n = max(cfg.rollout.n_workers, 1)
    eval_gym_kwargs = {**gym_kwargs, "rerun_dir": str(cfg.output_dir / "eval_rrd")} if cfg.eval_rerun else gym_kwargs
    return [
        {
            "make_env": partial(make_gym_env, cfg.env.gym_id, gym_kwargs),
            "make_eval_env": partial(make_gym_env, cfg.env.gym_id, eval_gym_kwargs),
            "make_agent": partial(BCRLAgent.from_pretrained, policy_dir),
            "n_envs": cfg.rollout.envs_per_worker,
            "seed": seed + 7919 * i,
        }
        for i in range(n)
    ]


# --------------------------------------------------------------------------------------------- main
def finetune(cfg: FinetuneConfig) -> dict:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.utils.random_utils import set_seed

    if cfg.policy is None:
        raise ValueError("give --policy.path=<BC pretrained_model> or --policy.type=bcrl (PPO from scratch)")
    if cfg.ppo.obs_normalization not in OBS_NORMALIZATION_MODES:
        raise ValueError(f"--ppo.obs_normalization={cfg.ppo.obs_normalization!r}: choose one of {OBS_NORMALIZATION_MODES}")
    if cfg.select not in SELECTIONS:
        raise ValueError(f"--select={cfg.select!r}: choose one of {SELECTIONS}")
    if cfg.select == "best_validation" and cfg.total_env_steps > 0 and not cfg.eval_freq:
        raise ValueError("--select=best_validation chooses among the periodic evaluations: give --eval_freq > 0")
    checkpoints_dir = cfg.output_dir / "checkpoints"
    last_checkpoint = checkpoints_dir / "last"
    set_critic(cfg.policy, cfg.ppo.critic_hidden_dims)
    if cfg.schedule.type == "auto":  # BC+RL decays theta_t from 1; from scratch there is no BC term at all
        from_checkpoint = cfg.policy.pretrained_path is not None
        cfg.schedule.type = "three_phase" if from_checkpoint else "constant"
        cfg.schedule.constant_theta = cfg.schedule.constant_theta if from_checkpoint else 0.0
    if cfg.resume:
        if not last_checkpoint.exists():
            raise FileNotFoundError(f"--resume=true but there is no checkpoint at {last_checkpoint}")
        initial_policy_path = cfg.policy.pretrained_path
        cfg.policy.pretrained_path = last_checkpoint.resolve() / "pretrained_model"
    elif (cfg.output_dir / "checkpoints").exists():
        raise FileExistsError(f"{cfg.output_dir} already holds checkpoints: pass --resume=true or another --output_dir")
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    set_seed(cfg.seed)
    torch.set_num_threads(1)

    dataset = LeRobotDataset(cfg.dataset.repo_id, root=cfg.dataset.root, episodes=cfg.dataset.episodes,
                             video_backend=cfg.dataset.video_backend)
    policy, preprocessor, postprocessor = build_policy(cfg, dataset)
    agent = BCRLAgent(policy, preprocessor)
    optimizer = torch.optim.Adam(policy.parameters(), lr=cfg.ppo.learning_rate, eps=1e-5)
    schedule_state, env_steps = ScheduleState(), 0
    best = None  # the validation evaluation behind checkpoints/best (--select=best_validation)
    reward_scaler = RewardScaler(cfg.ppo.gamma, cfg.rollout.n_envs) if cfg.ppo.normalize_rewards else None
    obs_stats = None
    if cfg.ppo.obs_normalization == "running":
        obs_stats = RunningObservationStats(find_normalizer(preprocessor), prior_count=dataset.num_frames)
    if cfg.resume:
        training_step = load_training_state(last_checkpoint, optimizer)
        env_steps = training_step["env_steps"]
        schedule_state = ScheduleState(training_step["optim_step"], training_step["ppo_iteration"])
        if reward_scaler and training_step["reward_scaler"]:
            reward_scaler.load_state_dict(training_step["reward_scaler"])
        if obs_stats and training_step.get("obs_stats"):
            obs_stats.load_state_dict(training_step["obs_stats"])
        best = training_step.get("best")
        cfg.policy.pretrained_path = initial_policy_path  # the run's origin, for the method label
    elif cfg.total_env_steps > 0:
        with torch.no_grad():  # log_std covers [delta_pos / scale (3), quaternion (4)]
            if cfg.ppo.reset_log_std is not None:
                policy.log_std[:3] = cfg.ppo.reset_log_std
            rotation_log_std = cfg.ppo.reset_log_std_rotation
            if rotation_log_std is None:
                rotation_log_std = cfg.ppo.reset_log_std
            if rotation_log_std is not None:
                policy.log_std[3:] = rotation_log_std
    if cfg.ppo.anneal_log_std_to is not None:
        policy.log_std.requires_grad_(False)  # a schedule, set before each iteration

    # The workers load config and processors once from disk; weights travel with every rollout request.
    policy_dir = cfg.output_dir / ROLLOUT_POLICY_DIR
    policy.save_pretrained(policy_dir)
    preprocessor.save_pretrained(policy_dir)
    postprocessor.save_pretrained(policy_dir)
    gym_kwargs = env_gym_kwargs(cfg, policy.config.uses_images)
    # Fresh worker seeds after a resume, so a resumed run does not replay the episodes it has seen.
    workers: RolloutWorkers = make_workers(
        cfg.rollout.n_workers, worker_kwargs(cfg, policy_dir, gym_kwargs, cfg.seed + 104_729 * schedule_state.ppo_iteration))
    demo_batches = DemoBuffer(dataset, cfg.bc_batch_size, cfg.seed + schedule_state.ppo_iteration, preprocessor)
    logger = RunLogger(cfg, env_steps if cfg.resume else None)
    steps_per_iteration = cfg.rollout.steps_per_iteration

    def evaluate(n_episodes: int, seed_offset: int, sample: bool = False) -> tuple[dict, list[EpisodeStats]]:
        seeds = list(range(seed_offset, seed_offset + n_episodes))
        annotations = {"theta_t": schedule_state.theta(cfg.schedule), "env_steps": env_steps}
        episodes = workers.evaluate(agent.state_dict(), seeds, annotations, sample)
        return summarize_episodes(episodes, "eval_sampled" if sample else "eval"), episodes

    def save() -> Path:
        nonlocal last_save
        last_save = env_steps
        return save_checkpoint(cfg, env_steps, agent, postprocessor, optimizer, schedule_state, reward_scaler,
                               obs_stats, best)

    def validate() -> dict:
        """A periodic evaluation; with --select=best_validation a better policy is saved as checkpoints/best."""
        nonlocal best
        metrics = evaluate(cfg.eval_episodes, VALIDATION_SEED_OFFSET)[0]
        candidate = {"env_steps": env_steps, "success": metrics["eval_success"], "return": metrics["eval_return"]}
        if cfg.select == "best_validation" and better_on_validation(candidate, best):
            best = candidate
            point_symlink(checkpoints_dir, "best", save())
        return metrics

    start_time, last_eval, last_save = time.time(), env_steps, env_steps
    progress = tqdm(total=cfg.total_env_steps, initial=env_steps, unit="step", desc=f"bcrl-finetune {cfg.method}")
    try:
        if cfg.select == "best_validation" and cfg.total_env_steps > 0 and best is None:  # the starting policy
            logger.log({"env_steps": env_steps, "ppo_iteration": schedule_state.ppo_iteration,
                        "optim_step": schedule_state.optim_step, "theta": schedule_state.theta(cfg.schedule),
                        "wall_s": time.time() - start_time, **validate()})
        while env_steps < cfg.total_env_steps:
            collect_start = time.time()
            position_log_std = position_log_std_at(cfg.ppo, env_steps, cfg.total_env_steps)
            if position_log_std is not None:
                with torch.no_grad():
                    policy.log_std[:3] = position_log_std
            trajectories = workers.collect(agent.state_dict(), cfg.rollout.steps_per_env)
            learning_rate = learning_rate_at(cfg.ppo, env_steps, cfg.total_env_steps)
            for group in optimizer.param_groups:
                group["lr"] = learning_rate
            env_steps += steps_per_iteration
            learn_start = time.time()
            rewards = reward_scaler(trajectories.rewards, trajectories.dones) if reward_scaler else trajectories.rewards
            metrics = ppo_update(agent, optimizer, trajectories, rewards, cfg.ppo, cfg.schedule, schedule_state,
                                 demo_batches, policy.forward)
            if obs_stats:  # after the update, so each batch was learnt with the stats it was collected with
                obs_stats.update(agent.lerobot_observation(low_dim_observations(trajectories)))
                obs_stats.apply()
            row = {"env_steps": env_steps, "ppo_iteration": schedule_state.ppo_iteration,
                   "optim_step": schedule_state.optim_step, "wall_s": time.time() - start_time,
                   "collect_s": learn_start - collect_start, "learn_s": time.time() - learn_start,
                   "learning_rate": learning_rate, "position_log_std": policy.log_std[:3].mean().item(),
                   **metrics, **summarize_episodes(trajectories.episodes, "train")}
            row["theta"] = schedule_state.theta(cfg.schedule)  # theta for the next update
            if cfg.eval_freq and env_steps - last_eval >= cfg.eval_freq:
                row.update(validate())
                last_eval = env_steps
            logger.log(row)
            progress.update(steps_per_iteration)
            progress.set_postfix(theta=f"{row['theta']:.3f}", ret=f"{row.get('train_return', float('nan')):.0f}",
                                 succ=f"{row.get('train_success', float('nan')):.2f}")
            if last_save != env_steps and (env_steps - last_save >= cfg.save_freq or env_steps >= cfg.total_env_steps):
                save()
        progress.close()
        if env_steps == 0 or not last_checkpoint.exists():  # BC only: still leave a checkpoint to evaluate
            save()
        if best is not None:  # the chosen policy, not the last, is the run's result
            agent.load_state_dict(BCRLAgent.from_pretrained(checkpoints_dir / "best" / "pretrained_model").state_dict())
        final, episodes = evaluate(cfg.final_eval_episodes, EVAL_SEED_OFFSET)
        if cfg.final_eval_sampled:
            sampled, sampled_episodes = evaluate(cfg.final_eval_episodes, EVAL_SEED_OFFSET, sample=True)
            final.update(sampled, episodes_sampled=[asdict(e) for e in sampled_episodes])
    finally:
        workers.close()
        logger.close()
    result = {"method": cfg.method, "env_steps": env_steps, "theta": schedule_state.theta(cfg.schedule),
              "optim_step": schedule_state.optim_step, "seed": cfg.seed, "dataset_root": str(Path(dataset.root).resolve()),
              "dataset_repo_id": cfg.dataset.repo_id, "wall_s": time.time() - start_time,
              # the policy this run started from, and the env steps already behind it (an evaluated checkpoint's)
              "policy_path": str(cfg.policy.pretrained_path) if cfg.policy.pretrained_path else None,
              "policy_env_steps": policy_env_steps(cfg.policy.pretrained_path),
              # the policy evaluated below: the last, or the one --select=best_validation chose, and why
              "select": cfg.select, "selected_env_steps": best["env_steps"] if best else env_steps,
              "validation": {**best, "seed_offset": VALIDATION_SEED_OFFSET, "episodes": cfg.eval_episodes} if best else None,
              **final,
              "episodes": [asdict(e) for e in episodes]}
    (cfg.output_dir / "eval_final.json").write_text(json.dumps(result, indent=2))
    return result


@parser.wrap()
def finetune_cli(cfg: FinetuneConfig) -> None:
    result = finetune(cfg)
    lines = [
        f"\nbcrl-finetune ({result['method']}): {result['env_steps']} env steps, {result['optim_step']} optimisation"
        f" steps, theta_t = {result['theta']:.4f}, {result['wall_s']:.0f} s",
        f"  final evaluation over {result['eval_episodes']} episodes: return {result['eval_return']:.1f}"
        f" +/- {result['eval_return_ci95']:.1f} (95 % CI), success {100 * result['eval_success']:.0f} %,"
        f" steps to lift {result['eval_steps_to_lift']:.1f}",
    ]
    if "eval_sampled_return" in result:
        lines.append(f"  with sampled actions: return {result['eval_sampled_return']:.1f}"
                     f" +/- {result['eval_sampled_return_ci95']:.1f}, success {100 * result['eval_sampled_success']:.0f} %")
    if result["validation"]:
        chosen = result["validation"]
        lines.append(f"  the policy at {result['selected_env_steps']} env steps, chosen on {chosen['episodes']} validation"
                     f" episodes (success {100 * chosen['success']:.0f} %, return {chosen['return']:.1f})")
    checkpoint = "best" if result["validation"] else "last"
    lines += [f"  checkpoint: {cfg.output_dir / 'checkpoints' / checkpoint / 'pretrained_model'}",
              f"  logs: {cfg.output_dir / 'logs.csv'}; evaluation: {cfg.output_dir / 'eval_final.json'}"]
    print("\n".join(lines))


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    os.environ.setdefault("MUJOCO_GL", "egl")
    finetune_cli()


if __name__ == "__main__":
    main()
