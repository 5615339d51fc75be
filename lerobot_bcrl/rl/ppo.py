"""BC+RL: PPO fine-tuning of a `bcrl` policy with a decaying BC term, `L = theta_t * L_BC + (1 - theta_t) * L_PPO`.

CleanRL-style, top to bottom: PPO's hyper-parameters, GAE, the loss, the update, and the loop (collect rollouts
from the workers, update, evaluate, checkpoint). Around it, a module each: configuration.py (the command line),
build.py, rollout.py (workers), schedule.py (theta_t), demo_buffer.py, checkpoint.py, logger.py.
"""

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from lerobot_bcrl import frame_cache
from lerobot_bcrl.files import write_json_atomically
from lerobot_bcrl.rl.agent import Agent, BCRLAgent
from lerobot_bcrl.rl.build import build_policy, reset_exploration_std, start_workers
from lerobot_bcrl.rl.checkpoint import (better_on_validation, checkpoint_name, load_training_state, point_symlink,
                                        policy_env_steps, save_checkpoint)
from lerobot_bcrl.rl.demo_buffer import DemoBuffer
from lerobot_bcrl.rl.logger import RunLogger, summarize_episodes
from lerobot_bcrl.rl.normalization import RewardScaler
from lerobot_bcrl.rl.rollout import Trajectories
from lerobot_bcrl.rl.schedule import ScheduleConfig, ScheduleState

EVAL_SEED_OFFSET = 1_000_000  # the final evaluation's (test) seeds: no dataset or training rollout draws them
VALIDATION_SEED_OFFSET = 2_000_000  # the periodic evaluations' seeds, which may choose the result: never the test's
ANALYSIS_SEED_OFFSET = 3_000_000  # scripts that look at a policy or the expert (scripts/): they choose nothing
TERM_WEIGHTINGS = ("loss", "gradient_share")


@dataclass
class PPOConfig:
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2  # clipped surrogate's epsilon
    c1: float = 1.0  # weight of the clipped surrogate in L_PPO (docs/method.md section 4)
    c2: float = 0.5  # weight of the value loss
    entropy_coef: float = 0.0  # bonus on the whole action's entropy
    # Bonus on the gripper class's entropy alone (agents whose `evaluate` names a "gripper" part): exploration of
    # when to close, which the continuous log-std does not give (the BC gripper is near-certain: ~0.01 nats). 0 in
    # the recipe: at 0.1 and 1.0 the gripper drifted to a coin flip once theta_t reached 0 (docs/RESULTS.md).
    gripper_entropy_coef: float = 0.0
    update_epochs: int = 4
    minibatch_size: int = 256
    learning_rate: float = 1e-4
    max_grad_norm: float = 0.5
    # Early stop (Spinning Up's, per minibatch): once a minibatch's approx-KL to the rollout policy exceeds this, the
    # iteration takes no more steps. None: every epoch runs (CleanRL's default).
    target_kl: float | None = None
    normalize_advantages: bool = True
    normalize_rewards: bool = True  # divide rewards by a running std of the discounted return (rl/normalization.py)
    # The exploration log-std set before the first update (build.reset_exploration_std), on [delta_pos / scale,
    # delta_rotvec / scale].
    reset_log_std: float = -1.5
    # How theta_t weighs the two terms. "loss": the paper's `theta * L_BC + (1 - theta) * L_PPO`. "gradient_share":
    # L_BC is first rescaled per minibatch by ||grad L_PPO|| / ||grad L_BC|| (policy term, detached; over the
    # agent's `term_norm_parameters`: an image policy's layers after its CNN), so theta_t is the BC term's share of
    # the policy gradient (PPO's was 2-9x the BC loss's here: docs/RESULTS.md).
    term_weighting: str = "loss"

    def __post_init__(self):
        if self.term_weighting not in TERM_WEIGHTINGS:
            raise ValueError(f"ppo.term_weighting must be one of {TERM_WEIGHTINGS}, got {self.term_weighting!r}")
        if self.target_kl is not None and self.target_kl <= 0:
            raise ValueError(f"ppo.target_kl must be positive (or None: no early stop), got {self.target_kl}")


# ------------------------------------------------------------------------------------------ PPO's maths
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


def gradient_norm(params: list[torch.nn.Parameter], term: Tensor) -> float:
    """||d term / d params||, without touching `.grad` (the graph is kept for the real backward pass)."""
    if not term.requires_grad:
        return 0.0
    grads = torch.autograd.grad(term, params, retain_graph=True, allow_unused=True)
    squares = [g.detach().pow(2).sum() for g in grads if g is not None]
    return float(torch.stack(squares).sum().sqrt()) if squares else 0.0


def term_gradient_norms(params: list[torch.nn.Parameter], bc_term: Tensor, ppo_term: Tensor) -> dict[str, float]:
    """Gradient norms of the weighted BC and PPO policy terms and the BC term's share of their sum: how much
    theta_t weighs once each term's gradient scale counts (logged once per iteration)."""
    bc_norm, ppo_norm = gradient_norm(params, bc_term), gradient_norm(params, ppo_term)
    share = bc_norm / (bc_norm + ppo_norm) if bc_norm + ppo_norm > 0 else float("nan")
    return {"bc_term_grad_norm": bc_norm, "ppo_term_grad_norm": ppo_norm, "bc_grad_share": share}


def bc_gradient_scale(params: list[torch.nn.Parameter], bc_loss: Tensor, ppo_loss: Tensor) -> float:
    """`||grad L_PPO|| / ||grad L_BC||` (1 when either is zero): gives L_BC the PPO policy term's gradient scale."""
    bc_norm, ppo_norm = gradient_norm(params, bc_loss), gradient_norm(params, ppo_loss)
    return ppo_norm / bc_norm if bc_norm > 0 and ppo_norm > 0 else 1.0


def bcrl_loss(agent: Agent, minibatch: dict, demo_batch: dict | None, theta: float, cfg: PPOConfig,
              bc_forward=None, measure_gradients: bool = False) -> tuple[Tensor, dict[str, float]]:
    """`theta * L_BC + (1 - theta) * L_PPO` on one PPO minibatch and one preprocessed demo minibatch."""
    new_log_prob, entropies, new_value = agent.evaluate(minibatch["obs"], minibatch["actions"])
    entropy = sum(entropies.values())
    advantages = minibatch["advantages"]
    if cfg.normalize_advantages and advantages.numel() > 1:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    ppo = ppo_loss_terms(new_log_prob, minibatch["log_probs"], advantages, new_value, minibatch["returns"], cfg.clip_eps)
    ppo_loss = cfg.c1 * ppo["policy_loss"] - cfg.entropy_coef * entropy.mean()
    if cfg.gripper_entropy_coef:
        if "gripper" not in entropies:
            raise ValueError(f"ppo.gripper_entropy_coef needs an agent with a gripper class, not {list(entropies)}")
        ppo_loss = ppo_loss - cfg.gripper_entropy_coef * entropies["gripper"].mean()
    value_loss = cfg.c2 * ppo["value_loss"]
    # No demo forward pass when the BC term has no weight (pure PPO, or after phi).
    bc_start = time.perf_counter()
    bc_loss, metrics = bc_forward(demo_batch) if theta > 0 else (torch.zeros(()), {})
    if cfg.term_weighting == "gradient_share" and theta > 0:
        metrics["bc_scale"] = bc_gradient_scale(agent.term_norm_parameters(), bc_loss, ppo_loss)
        bc_loss = metrics["bc_scale"] * bc_loss
    bc_term_s = time.perf_counter() - bc_start  # the BC forward pass and the gradient-share norms (not its backward)
    if measure_gradients:
        metrics.update(term_gradient_norms(agent.term_norm_parameters(), theta * bc_loss, (1 - theta) * ppo_loss))

    # The value loss stands outside (1 - theta): the critic learns from the first update, so PPO does not start on
    # an untrained one (the paper's form weighs it with the policy term: docs/bcrl_finetune.md).
    loss = theta * bc_loss + (1 - theta) * ppo_loss + value_loss

    metrics.update({name: float(value.detach()) for name, value in ppo.items()})
    metrics.update({f"{part}_entropy": float(value.mean().detach()) for part, value in entropies.items()})
    metrics.update(entropy=float(entropy.mean().detach()), ppo_loss=float(ppo_loss.detach()), loss=float(loss.detach()),
                   bc_term_s=bc_term_s)
    return loss, metrics


# ----------------------------------------------------------------------------------------- the update
def training_batch(trajectories: Trajectories, rewards: np.ndarray, cfg: PPOConfig) -> dict:
    """GAE advantages and returns (time-limit truncations bootstrapped from their value), flattened to samples."""
    values = torch.as_tensor(trajectories.values)
    bootstrapped_rewards = torch.as_tensor(rewards) + cfg.gamma * torch.as_tensor(trajectories.truncation_values)
    advantages, returns = compute_gae(bootstrapped_rewards, values, torch.as_tensor(trajectories.dones),
                                      torch.as_tensor(trajectories.last_values), cfg.gamma, cfg.gae_lambda)
    flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731  (T, N, ...) -> (T*N, ...)
    return {
        "obs": {key: flat(value) for key, value in trajectories.observations.items()},
        "actions": flat(torch.as_tensor(trajectories.actions)),
        "log_probs": flat(torch.as_tensor(trajectories.log_probs)),
        "values": flat(values),
        "advantages": flat(advantages),
        "returns": flat(returns),
    }


def select_minibatch(agent: Agent, batch: dict, index: Tensor) -> dict:
    """Rows `index` of a training batch, observations through the agent's preprocessing."""
    minibatch = {key: value[index] for key, value in batch.items() if key != "obs"}
    minibatch["obs"] = agent.observation_batch({k: v[index.numpy()] for k, v in batch["obs"].items()})
    return minibatch


def ppo_update(agent: Agent, optimizer: torch.optim.Optimizer, trajectories: Trajectories, rewards: np.ndarray,
               cfg: PPOConfig, schedule_cfg: ScheduleConfig, schedule_state: ScheduleState,
               demo_batches=None, bc_forward=None) -> dict[str, float]:
    """One PPO iteration: GAE, then `update_epochs` passes over shuffled minibatches (fewer where `target_kl` stops
    them: `optim_steps_taken`, `kl_stopped`); returns mean metrics and the seconds spent reading minibatches
    (`learner_data_s`), in the BC term's forward pass and gradient-share norms (`bc_term_s`) and in the rest: PPO's
    forward pass, the joint loss's backward pass and the step (`update_s`)."""
    update_start = time.perf_counter()
    batch = training_batch(trajectories, rewards, cfg)
    batch_size = batch["actions"].shape[0]
    agent.module.train()
    history: dict[str, list[float]] = {}
    data_s = bc_term_s = 0.0
    first_step, kl_stopped = schedule_state.optim_step, False
    for epoch in range(cfg.update_epochs):
        permutation = torch.randperm(batch_size)
        for start in range(0, batch_size, cfg.minibatch_size):
            data_start = time.perf_counter()
            minibatch = select_minibatch(agent, batch, permutation[start : start + cfg.minibatch_size])
            theta = schedule_state.theta(schedule_cfg)
            demo_batch = next(demo_batches) if (theta > 0 and demo_batches is not None) else None
            data_s += time.perf_counter() - data_start
            loss, metrics = bcrl_loss(agent, minibatch, demo_batch, theta, cfg, bc_forward,
                                      measure_gradients=epoch == 0 and start == 0)  # once per iteration
            bc_term_s += metrics.pop("bc_term_s")
            kl_stopped = cfg.target_kl is not None and metrics["approx_kl"] > cfg.target_kl
            if kl_stopped:
                break
            optimizer.zero_grad()
            loss.backward()
            metrics["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(agent.module.parameters(), cfg.max_grad_norm))
            optimizer.step()
            schedule_state.optim_step += 1
            for name, value in {**metrics, "theta": theta}.items():
                history.setdefault(name, []).append(value)
        if kl_stopped:
            break
    schedule_state.ppo_iteration += 1
    summary = {name: float(np.mean(values)) for name, values in history.items()}
    summary.update(optim_steps_taken=schedule_state.optim_step - first_step, kl_stopped=float(kl_stopped))
    summary["explained_variance"] = explained_variance(batch["values"].numpy(), batch["returns"].numpy())
    summary.update(learner_data_s=data_s, bc_term_s=bc_term_s,
                   update_s=time.perf_counter() - update_start - data_s - bc_term_s)
    return summary


# ------------------------------------------------------------------------------------------- the loop
def finetune(cfg) -> dict:
    """A bcrl-finetune run (rl/configuration.FinetuneConfig): train, choose the result, evaluate it on test seeds."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.utils.random_utils import set_seed

    cfg.validate()
    checkpoints_dir = cfg.output_dir / "checkpoints"
    if cfg.schedule.type == "auto":  # BC+RL decays theta_t from 1; from scratch there is no BC term at all
        from_checkpoint = cfg.policy.pretrained_path is not None
        cfg.schedule.type = "three_phase" if from_checkpoint else "constant"
        cfg.schedule.constant_theta = cfg.schedule.constant_theta if from_checkpoint else 0.0
    initial_policy_path = cfg.policy.pretrained_path  # the run's origin (a resume loads its last checkpoint)
    if cfg.resume:
        cfg.policy.pretrained_path = (checkpoints_dir / "last").resolve() / "pretrained_model"
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    set_seed(cfg.seed)
    torch.set_num_threads(1)

    dataset = LeRobotDataset(cfg.dataset.repo_id, root=cfg.dataset.root, episodes=cfg.dataset.episodes,
                             video_backend=cfg.dataset.video_backend)
    policy, preprocessor, postprocessor = build_policy(cfg.policy, dataset)
    agent = BCRLAgent(policy, preprocessor)
    optimizer = torch.optim.Adam(policy.parameters(), lr=cfg.ppo.learning_rate, eps=1e-5)
    reward_scaler = RewardScaler(cfg.ppo.gamma, cfg.rollout.n_envs) if cfg.ppo.normalize_rewards else None
    schedule, env_steps, best = ScheduleState(), 0, None  # best: the validation evaluation behind checkpoints/best
    validations = []  # every periodic evaluation: {env_steps, success, return}
    if cfg.resume:
        state = load_training_state(checkpoints_dir / "last", optimizer)
        schedule, env_steps, best = ScheduleState(state["optim_step"], state["ppo_iteration"]), state["env_steps"], state["best"]
        validations = state["validations"]
        if reward_scaler and state["reward_scaler"]:
            reward_scaler.load_state_dict(state["reward_scaler"])
        cfg.policy.pretrained_path = initial_policy_path
    elif cfg.total_env_steps > 0:
        reset_exploration_std(policy, cfg.ppo.reset_log_std)
    # Fresh worker seeds after a resume, so a resumed run does not replay the episodes it has seen.
    workers = start_workers(cfg, policy, preprocessor, postprocessor, cfg.seed + 104_729 * schedule.ppo_iteration)
    demo_batches = (DemoBuffer(dataset, cfg.bc_batch_size, cfg.seed + schedule.ppo_iteration, preprocessor)
                    if env_steps < cfg.total_env_steps else None)  # an evaluation-only run never reads them
    frame_cache.clear()  # the buffer holds its own copy of the frames
    logger = RunLogger(cfg, env_steps if cfg.resume else None)

    def evaluate(n_episodes: int, seed_offset: int) -> tuple[dict, list]:
        annotations = {"theta_t": schedule.theta(cfg.schedule), "env_steps": env_steps}
        episodes = workers.evaluate(agent.state_dict(), list(range(seed_offset, seed_offset + n_episodes)), annotations)
        return summarize_episodes(episodes, "eval"), episodes

    def save():
        nonlocal last_save
        last_save = env_steps
        return save_checkpoint(cfg, env_steps, agent, postprocessor, optimizer, schedule, reward_scaler, best, validations)

    def validate() -> dict:
        """A periodic evaluation; with --select=best_validation a better policy is saved as checkpoints/best, and
        with --reselect_episodes one that ties its success is saved too, to be evaluated again at the end."""
        nonlocal best
        metrics = evaluate(cfg.eval_episodes, VALIDATION_SEED_OFFSET)[0]
        candidate = {"env_steps": env_steps, "success": metrics["eval_success"], "return": metrics["eval_return"]}
        validations.append(candidate)
        if cfg.select == "best_validation" and better_on_validation(candidate, best):
            best = candidate
            point_symlink(checkpoints_dir, "best", save())
        elif cfg.reselect_episodes and candidate["success"] == best["success"]:
            save()
        return metrics

    def reselect() -> dict:
        """The saved policies whose validation tied the best success, each evaluated on the next
        --reselect_episodes validation seeds: the best over all its validation episodes (success, then return; the
        earliest of equals) becomes checkpoints/best."""
        first, more = cfg.eval_episodes, cfg.reselect_episodes
        tied = [v for v in validations if v["success"] == best["success"]
                and (checkpoints_dir / checkpoint_name(v["env_steps"])).exists()]
        pooled = []
        for v in tqdm(tied, desc=f"reselect on {more} more validation episodes", unit="policy"):
            checkpoint = checkpoints_dir / checkpoint_name(v["env_steps"]) / "pretrained_model"
            agent.load_state_dict(BCRLAgent.from_pretrained(checkpoint).state_dict())
            again = evaluate(more, VALIDATION_SEED_OFFSET + first)[0]
            pooled.append({"env_steps": v["env_steps"], "episodes": first + more,
                           "success": (first * v["success"] + more * again["eval_success"]) / (first + more),
                           "return": (first * v["return"] + more * again["eval_return"]) / (first + more)})
        chosen = max(pooled, key=lambda p: (p["success"], p["return"]))  # max keeps the earliest of equals
        point_symlink(checkpoints_dir, "best", checkpoints_dir / checkpoint_name(chosen["env_steps"]))
        return {**chosen, "first_choice": best, "candidates": pooled}

    start_time, last_eval, last_save, last_train = time.time(), env_steps, env_steps, {}
    progress = tqdm(total=cfg.total_env_steps, initial=env_steps, unit="step", desc=f"bcrl-finetune {cfg.method}",
                    disable=cfg.total_env_steps == 0)
    try:
        if cfg.select == "best_validation" and cfg.total_env_steps > 0 and best is None:  # the starting policy
            logger.log({"env_steps": env_steps, "ppo_iteration": schedule.ppo_iteration, "optim_step": schedule.optim_step,
                        "theta": schedule.theta(cfg.schedule), "wall_s": time.time() - start_time, **validate()})
        while env_steps < cfg.total_env_steps:
            collect_start = time.time()
            trajectories = workers.collect(agent.state_dict(), cfg.rollout.steps_per_env)
            env_steps += cfg.rollout.steps_per_iteration
            learn_start = time.time()
            rewards = reward_scaler(trajectories.rewards, trajectories.dones) if reward_scaler else trajectories.rewards
            torch.set_num_threads(cfg.learner_threads)  # the workers wait for the new weights meanwhile
            metrics = ppo_update(agent, optimizer, trajectories, rewards, cfg.ppo, cfg.schedule, schedule,
                                 demo_batches, policy.forward)
            torch.set_num_threads(1)  # an in-process worker (n_workers=0) steps its envs in this process
            train = summarize_episodes(trajectories.episodes, "train")
            last_train = train or last_train  # the progress bar shows the last finished episodes
            row = {"env_steps": env_steps, "ppo_iteration": schedule.ppo_iteration, "optim_step": schedule.optim_step,
                   "wall_s": time.time() - start_time, "collect_s": learn_start - collect_start,
                   "learn_s": time.time() - learn_start, "worker_restarts": workers.restarts, **metrics, **train,
                   **{f"{part}_s": seconds for part, seconds in trajectories.seconds.items()},
                   "theta": schedule.theta(cfg.schedule)}  # theta for the next update
            if cfg.eval_freq and env_steps - last_eval >= cfg.eval_freq:
                row.update(validate())
                last_eval = env_steps
            logger.log(row)
            progress.update(cfg.rollout.steps_per_iteration)
            progress.set_postfix(theta=f"{row['theta']:.3f}", **({"ret": f"{last_train['train_return']:.0f}",
                                 "succ": f"{last_train['train_success']:.2f}"} if last_train else {}))
            if last_save != env_steps and (env_steps - last_save >= cfg.save_freq or env_steps >= cfg.total_env_steps):
                save()
        progress.close()
        if not (checkpoints_dir / "last").exists():  # BC only: still leave a checkpoint to evaluate
            save()
        chosen = {**best, "episodes": cfg.eval_episodes} if best else None
        if best is not None and cfg.reselect_episodes:
            chosen = reselect()
        if chosen is not None:  # the chosen policy, not the last, is the run's result
            agent.load_state_dict(BCRLAgent.from_pretrained(checkpoints_dir / "best" / "pretrained_model").state_dict())
        final, episodes = evaluate(cfg.final_eval_episodes, EVAL_SEED_OFFSET)
    finally:
        workers.close()
        logger.close()
    result = {"method": cfg.method, "env_steps": env_steps, "theta": schedule.theta(cfg.schedule),
              "optim_step": schedule.optim_step, "seed": cfg.seed, "dataset_root": str(Path(dataset.root).resolve()),
              "dataset_repo_id": cfg.dataset.repo_id, "wall_s": time.time() - start_time,
              # the policy this run started from, and the env steps already behind it (an evaluated checkpoint's)
              "policy_path": str(cfg.policy.pretrained_path) if cfg.policy.pretrained_path else None,
              "policy_env_steps": policy_env_steps(cfg.policy.pretrained_path),
              # the policy evaluated below: the last, or the one --select=best_validation chose, and why
              "select": cfg.select, "selected_env_steps": chosen["env_steps"] if chosen else env_steps,
              "validation": {**chosen, "seed_offset": VALIDATION_SEED_OFFSET} if chosen else None,
              **final, "episodes": [asdict(e) for e in episodes]}
    write_json_atomically(cfg.output_dir / "eval_final.json", result)
    return result
