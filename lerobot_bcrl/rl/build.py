"""What a bcrl-finetune run is built from: the policy and its processors (as lerobot-train builds them), its
exploration std, and the rollout workers' recipes (envs, agent, seeds).
"""

from __future__ import annotations

import contextlib
import io
from functools import partial

import torch

from lerobot_bcrl.rl.agent import BCRLAgent
from lerobot_bcrl.rl.rollout import RolloutWorkers, make_gym_env, make_workers

ROLLOUT_POLICY_DIR = "rollout_policy"  # what the workers load once (config, processors); weights come per rollout


def build_policy(policy_cfg, dataset):
    """The policy and processors the way lerobot-train builds them (from a checkpoint or from scratch), on the CPU."""
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    policy_cfg.device = "cpu"
    with contextlib.redirect_stdout(io.StringIO()):  # LeRobot prints "Loading weights from local directory"
        policy = make_policy(policy_cfg, ds_meta=dataset.meta)
    pretrained = str(policy_cfg.pretrained_path) if policy_cfg.pretrained_path else None
    processor_kwargs = {"dataset_stats": dataset.meta.stats} if pretrained is None else {
        "preprocessor_overrides": {"device_processor": {"device": "cpu"}}}
    preprocessor, postprocessor = make_pre_post_processors(policy_cfg, pretrained_path=pretrained, **processor_kwargs)
    return policy, preprocessor, postprocessor


@torch.no_grad()
def reset_exploration_std(policy, log_std: float) -> None:
    """PPO's starting log-std over [delta_pos / scale (3), delta_rotvec / scale (3)]: BC never trains it. Both
    targets are scaled to the same size, so one value serves both."""
    policy.log_std.fill_(log_std)


def start_workers(cfg, policy, preprocessor, postprocessor, seed: int) -> RolloutWorkers:
    """Rollout workers that load the policy's config and processors once, from the files saved in
    `<output_dir>/rollout_policy` and sent along (no shared disk needed); weights travel with every request. A
    low-dim policy's envs skip the camera (3x faster)."""
    policy_dir = cfg.output_dir / ROLLOUT_POLICY_DIR
    for part in (policy, preprocessor, postprocessor):
        part.save_pretrained(policy_dir)
    gym_kwargs = dict(cfg.env.gym_kwargs)
    if not policy.config.uses_images:
        gym_kwargs["obs_type"] = "agent_pos"
    policy_files = {path.name: path.read_bytes() for path in sorted(policy_dir.iterdir())}  # a cluster's nodes too
    eval_gym_kwargs = {**gym_kwargs, "rerun_dir": str(cfg.output_dir / "eval_rrd")} if cfg.eval_rerun else gym_kwargs
    train_gym_kwargs = {**gym_kwargs, "dense_reward": True} if cfg.rollout.dense_reward else gym_kwargs
    worker_kwargs = [
        {
            "make_env": partial(make_gym_env, cfg.env.gym_id, train_gym_kwargs),
            "make_eval_env": partial(make_gym_env, cfg.env.gym_id, eval_gym_kwargs),
            "make_agent": partial(BCRLAgent.from_files, policy_files),
            "n_envs": cfg.rollout.envs_per_worker,
            "seed": seed + 7919 * i,
            "noise_color_beta": cfg.rollout.noise_color_beta,
        }
        for i in range(max(cfg.rollout.n_workers, 1))
    ]
    rollout = cfg.rollout
    return make_workers(worker_kwargs, rollout.n_workers, rollout.backend, rollout.ray_address, rollout.timeout_s,
                        rollout.max_worker_failures)
