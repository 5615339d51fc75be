"""How much does the BC term weigh in a BC+RL update? For a bcrl-finetune checkpoint: collect one rollout with
its run's settings, then on each minibatch measure the gradient norms of the BC loss and of PPO's policy term,
unweighted, and the BC term's share once weighted by the checkpoint's theta_t (`ppo.term_gradient_norms`). Runs that
started after this script log the weighted norms and the BC share once per iteration (`logs.csv`); this
measures checkpoints of earlier runs the same way.

It also says how much of each gradient is signal: the rollout's env copies are split into two halves (independent
episodes), each term's gradient is averaged over each half's minibatches (BC: as many fresh demo minibatches), and
the cosine between the halves' gradients is reported (`*_half_cosine`: ~1 when the batch pins the gradient down,
~0 when it is sampling noise), with the cosine between the PPO and BC gradients of the whole rollout.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 .venv/bin/python scripts/measure_term_gradients.py \
        outputs/.../bcrl/checkpoints/000044800 [--rollout_seed=12345]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import draccus
import numpy as np
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_bcrl.rl import ppo
from lerobot_bcrl.rl.agent import BCRLAgent
from lerobot_bcrl.rl.normalization import RewardScaler
from lerobot_bcrl.rl.rollout import make_workers
from lerobot_bcrl.rl.schedule import ScheduleState


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path, help="checkpoints/<step> of a bcrl-finetune run")
    parser.add_argument("--rollout_seed", type=int, default=12345)
    parser.add_argument("--position_log_std", type=float, default=None,
                        help="measure with this log-std of delta_pos instead of the checkpoint's")
    parser.add_argument("--gae_lambda", type=float, default=None, help="advantages with this GAE lambda instead of the run's")
    args = parser.parse_args()
    pretrained = args.checkpoint / "pretrained_model"
    with open(pretrained / ppo.FINETUNE_CONFIG_NAME) as f, draccus.config_type("json"):
        cfg = draccus.load(ppo.FinetuneConfig, f)
    training_step = json.loads((args.checkpoint / "training_state" / ppo.TRAINING_STEP_FILE).read_text())
    # the raw norms of both terms, whichever weighting the run used
    cfg.ppo = dataclasses.replace(cfg.ppo, term_weighting="loss")
    if args.gae_lambda is not None:
        cfg.ppo.gae_lambda = args.gae_lambda
    theta = ScheduleState(training_step["optim_step"], training_step["ppo_iteration"]).theta(cfg.schedule)
    torch.manual_seed(args.rollout_seed)
    agent = BCRLAgent.from_pretrained(pretrained)
    if args.position_log_std is not None:
        with torch.no_grad():
            agent.policy.log_std[:3] = args.position_log_std

    # the run's rollout: its env copies, collected inline (one process), rewards scaled as the run scaled them
    n_envs = max(cfg.rollout.n_workers, 1) * cfg.rollout.envs_per_worker
    kwargs = ppo.worker_kwargs(cfg, pretrained, ppo.env_gym_kwargs(cfg, agent.policy.config.uses_images), args.rollout_seed)
    workers = make_workers(0, kwargs)
    trajectories = workers.collect(agent.state_dict(), cfg.rollout.steps_per_env)
    workers.close()
    scaler = RewardScaler(cfg.ppo.gamma, n_envs)
    if training_step.get("reward_scaler"):
        scaler.load_state_dict(training_step["reward_scaler"])
    rewards = scaler(trajectories.rewards, trajectories.dones) if cfg.ppo.normalize_rewards else trajectories.rewards
    batch = ppo.training_batch(trajectories, rewards, cfg.ppo)

    dataset = LeRobotDataset(cfg.dataset.repo_id, root=cfg.dataset.root)
    demo_batches = ppo.DemoBuffer(dataset, cfg.bc_batch_size, args.rollout_seed, agent.preprocessor)
    agent.module.train()
    rows = []  # theta = 0.5 weighs both terms alike: twice the logged norms are the unweighted ones
    n_samples = batch["actions"].shape[0]
    for start in range(0, n_samples, cfg.ppo.minibatch_size):
        index = torch.arange(start, min(start + cfg.ppo.minibatch_size, n_samples))
        minibatch = ppo.select_minibatch(agent, batch, index)
        _, metrics = ppo.bcrl_loss(agent, minibatch, next(demo_batches), 0.5, cfg.ppo, agent.policy.forward,
                                   measure_gradients=True)
        rows.append([2 * metrics["bc_term_grad_norm"], 2 * metrics["ppo_term_grad_norm"]])
    bc_norm, ppo_norm = np.mean(rows, axis=0)
    coherence = split_half_cosines(agent, batch, n_envs, demo_batches, cfg.ppo)
    weighted_bc, weighted_ppo = theta * bc_norm, (1 - theta) * ppo_norm
    print(json.dumps({
        "checkpoint": str(args.checkpoint), "position_log_std": round(float(agent.policy.log_std[:3].mean()), 3),
        "gae_lambda": cfg.ppo.gae_lambda,
        "env_steps": training_step["env_steps"], "theta": round(theta, 4),
        "rollout_success": float(np.mean([e.success for e in trajectories.episodes])) if trajectories.episodes else None,
        "bc_grad_norm": round(bc_norm, 3), "ppo_policy_grad_norm": round(ppo_norm, 3),
        "bc_grad_share_at_theta": round(weighted_bc / (weighted_bc + weighted_ppo), 3),
        "theta_for_an_even_share": round(ppo_norm / (bc_norm + ppo_norm), 3),
        **{name: round(value, 3) for name, value in coherence.items()},
    }))


def split_half_cosines(agent, batch: dict, n_envs: int, demo_batches, ppo_cfg) -> dict[str, float]:
    """Cosines between the mean gradients of two halves of the rollout (by env copy), per term, and between the
    whole rollout's PPO and BC gradients."""
    env_of_sample = torch.arange(batch["actions"].shape[0]) % n_envs  # samples are flattened time-major
    cosine = lambda a, b: float(torch.nn.functional.cosine_similarity(a, b, dim=0))  # noqa: E731
    means = {}
    for half, envs_mask in (("a", env_of_sample < n_envs // 2), ("b", env_of_sample >= n_envs // 2)):
        samples = torch.nonzero(envs_mask).squeeze(1)
        ppo_grads, bc_grads = [], []
        for start in range(0, len(samples), ppo_cfg.minibatch_size):
            minibatch = ppo.select_minibatch(agent, batch, samples[start : start + ppo_cfg.minibatch_size])
            _, _, policy_loss, _ = ppo.ppo_losses(agent, minibatch, ppo_cfg)
            bc_loss, _ = agent.policy.forward(next(demo_batches))
            ppo_grads.append(ppo.flat_gradient(agent.module, policy_loss))
            bc_grads.append(ppo.flat_gradient(agent.module, bc_loss))
        means[half] = (torch.stack(ppo_grads).mean(0), torch.stack(bc_grads).mean(0))
    (ppo_a, bc_a), (ppo_b, bc_b) = means["a"], means["b"]
    return {"ppo_half_cosine": cosine(ppo_a, ppo_b), "bc_half_cosine": cosine(bc_a, bc_b),
            "ppo_bc_cosine": cosine(ppo_a + ppo_b, bc_a + bc_b)}


if __name__ == "__main__":
    main()
