"""Rollout throughput of bcrl-finetune's workers with 1, 2, 4 subprocesses against a single env in this process,
and the share of a PPO iteration's wall time spent in simulation vs learning. Prints one JSON line."""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from functools import partial
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch  # noqa: E402


def build_policy_dir(tmp: Path, dataset_root: str | None) -> Path:
    """A fresh low-dim bcrl policy saved like bcrl-finetune's rollout policy (features from the env config)."""
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    from lerobot_bcrl.envs.configuration_lift import LiftEnvConfig
    from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig

    cfg = BCRLConfig(device="cpu", push_to_hub=False, observation_mode="low_dim", require_aux_targets=False)
    policy = make_policy(cfg, env_cfg=LiftEnvConfig(obs_type="agent_pos"))
    preprocessor, postprocessor = make_pre_post_processors(cfg, dataset_stats=None)
    for part in (policy, preprocessor, postprocessor):
        part.save_pretrained(tmp / "policy")
    return tmp / "policy"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps_per_env", type=int, default=200)
    parser.add_argument("--envs_per_worker", type=int, default=1)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    args = parser.parse_args()
    torch.set_num_threads(1)

    from lerobot_bcrl.envs.configuration_lift import LiftEnvConfig
    from lerobot_bcrl.rl.agent import BCRLAgent
    from lerobot_bcrl.rl.ppo import PPOConfig, ppo_update
    from lerobot_bcrl.rl.rollout import InlineWorkers, ProcessWorkers, make_gym_env
    from lerobot_bcrl.rl.schedule import ScheduleConfig, ScheduleState

    env_cfg = LiftEnvConfig(obs_type="agent_pos")
    with tempfile.TemporaryDirectory() as tmp:
        policy_dir = build_policy_dir(Path(tmp), None)
        kwargs = lambda i: {"make_env": partial(make_gym_env, env_cfg.gym_id, env_cfg.gym_kwargs),  # noqa: E731
                            "make_agent": partial(BCRLAgent.from_pretrained, policy_dir),
                            "n_envs": args.envs_per_worker, "seed": i}
        # Baseline: the same worker code, one env, in this process (simulation + policy forward per step).
        single = InlineWorkers([{**kwargs(0), "n_envs": 1}])
        state = single.workers[0].agent.module.state_dict()
        single.collect(state, 5)
        start = time.perf_counter()
        single.collect(state, args.steps_per_env)
        single_sps = args.steps_per_env / (time.perf_counter() - start)
        single.close()

        result = {"bench": "rollout_throughput", "cpu_count": os.cpu_count(), "single_env_steps_per_s": round(single_sps, 1)}
        for n in args.workers:
            workers = ProcessWorkers([kwargs(i) for i in range(n)])
            workers.collect(state, 5)  # warm-up: imports, first render of each env
            start = time.perf_counter()
            trajectories = workers.collect(state, args.steps_per_env)
            collect_s = time.perf_counter() - start
            sps = n * args.envs_per_worker * args.steps_per_env / collect_s
            result[f"workers_{n}_steps_per_s"] = round(sps, 1)
            result[f"workers_{n}_scaling"] = round(sps / single_sps, 2)
            if n == args.workers[0]:  # one PPO update on this rollout: the learning side of an iteration
                agent = BCRLAgent.from_pretrained(policy_dir)
                optimizer = torch.optim.Adam(agent.module.parameters(), lr=3e-5)
                start = time.perf_counter()
                ppo_update(agent, optimizer, trajectories, trajectories.rewards, PPOConfig(minibatch_size=128),
                           ScheduleConfig(type="constant", constant_theta=0.0), ScheduleState())
                learn_s = time.perf_counter() - start
                result["simulation_share"] = round(collect_s / (collect_s + learn_s), 3)
                result["learning_share"] = round(learn_s / (collect_s + learn_s), 3)
            workers.close()
    print(json.dumps(result))


if __name__ == "__main__":
    main()
