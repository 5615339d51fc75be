"""Rollout throughput of bcrl-finetune's workers, one JSON line per backend: a single env in this process (the
baseline), then 1, 2, 4 workers as subprocesses and as Ray actors (a Ray on loopback, started here): env steps/s,
the scaling against the single env, and each backend's fixed cost per iteration (a 1-step collect: weights out,
trajectories back). The process line adds the share of a PPO iteration spent simulating vs learning.

`--ray_cluster` instead starts a two-node Ray cluster on this machine's loopback (`ray start --head` and `ray start
--address=...`, one CPU each: `lerobot_bcrl.rl.loopback_cluster`), collects with one actor per node through
`ray_address`, prints one JSON line, and stops both nodes."""

from __future__ import annotations

import argparse
import json
import os
import statistics
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


def worker_kwargs(policy_dir: Path, n_workers: int, envs_per_worker: int) -> list[dict]:
    from lerobot_bcrl.envs.configuration_lift import LiftEnvConfig
    from lerobot_bcrl.rl.agent import BCRLAgent
    from lerobot_bcrl.rl.rollout import make_gym_env

    env_cfg = LiftEnvConfig(obs_type="agent_pos")
    files = {path.name: path.read_bytes() for path in policy_dir.iterdir()}  # as bcrl-finetune sends them
    return [{"make_env": partial(make_gym_env, env_cfg.gym_id, env_cfg.gym_kwargs),
             "make_agent": partial(BCRLAgent.from_files, files), "n_envs": envs_per_worker, "seed": i}
            for i in range(n_workers)]


def measure(workers, state: dict, n_envs: int, steps_per_env: int) -> tuple[float, float, object]:
    """Env steps/s of one `steps_per_env` collect, the median wall time (s) of five 1-step collects, and the
    trajectories of the long one."""
    workers.collect(state, 5)  # warm-up: imports, first steps of each env
    start = time.perf_counter()
    trajectories = workers.collect(state, steps_per_env)
    steps_per_s = n_envs * steps_per_env / (time.perf_counter() - start)
    one_step_s = []
    for _ in range(5):
        start = time.perf_counter()
        workers.collect(state, 1)
        one_step_s.append(time.perf_counter() - start)
    return steps_per_s, statistics.median(one_step_s), trajectories


def learning_share(policy_dir: Path, trajectories, collect_s: float) -> dict:
    """One PPO update on a rollout: the learning side of an iteration, against the collect's wall time."""
    from lerobot_bcrl.rl.agent import BCRLAgent
    from lerobot_bcrl.rl.ppo import PPOConfig, ppo_update
    from lerobot_bcrl.rl.schedule import ScheduleConfig, ScheduleState

    agent = BCRLAgent.from_pretrained(policy_dir)
    optimizer = torch.optim.Adam(agent.module.parameters(), lr=3e-5)
    start = time.perf_counter()
    ppo_update(agent, optimizer, trajectories, trajectories.rewards, PPOConfig(minibatch_size=128),
               ScheduleConfig(type="constant", constant_theta=0.0), ScheduleState())
    learn_s = time.perf_counter() - start
    return {"simulation_share": round(collect_s / (collect_s + learn_s), 3),
            "learning_share": round(learn_s / (collect_s + learn_s), 3)}


def backends(args, policy_dir: Path) -> None:
    from lerobot_bcrl.rl.rollout import InlineWorkers, make_workers

    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # this Ray stays on loopback
    import ray

    single = InlineWorkers(worker_kwargs(policy_dir, 1, 1))
    state = single.workers[0].agent.module.state_dict()
    single_sps, single_overhead_s, _ = measure(single, state, 1, args.steps_per_env)
    single.close()
    common = {"bench": "rollout_throughput", "cpu_count": os.cpu_count(), "steps_per_env": args.steps_per_env,
              "envs_per_worker": args.envs_per_worker}
    print(json.dumps({**common, "backend": "single_env", "steps_per_s": round(single_sps, 1),
                      "one_step_collect_ms": round(1000 * single_overhead_s, 1)}), flush=True)

    ray.init(address="local", num_cpus=max(args.workers), _node_ip_address="127.0.0.1", include_dashboard=False)
    for backend in ("process", "ray"):
        result = {**common, "backend": backend}
        for n in args.workers:
            workers = make_workers(worker_kwargs(policy_dir, n, args.envs_per_worker), n, backend)
            try:
                sps, one_step_s, trajectories = measure(workers, state, n * args.envs_per_worker, args.steps_per_env)
            finally:
                workers.close()
            result[f"workers_{n}_steps_per_s"] = round(sps, 1)
            result[f"workers_{n}_scaling"] = round(sps / single_sps, 2)
            # the fixed cost of an iteration beyond the single env's: weights out, trajectories back
            result[f"workers_{n}_overhead_ms_per_iteration"] = round(1000 * (one_step_s - single_overhead_s), 1)
            if backend == "process" and n == args.workers[0]:
                collect_s = n * args.envs_per_worker * args.steps_per_env / sps
                result.update(learning_share(policy_dir, trajectories, collect_s))
        print(json.dumps(result), flush=True)
    ray.shutdown()


def ray_cluster(args, policy_dir: Path) -> None:
    """Two nodes of one CPU each on loopback (`LoopbackCluster`); the actors join through `ray_address`."""
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # this driver joins on loopback
    import ray

    from lerobot_bcrl.rl.agent import BCRLAgent
    from lerobot_bcrl.rl.loopback_cluster import LoopbackCluster
    from lerobot_bcrl.rl.rollout import make_workers

    with LoopbackCluster([1, 1]) as cluster:
        workers = make_workers(worker_kwargs(policy_dir, 2, args.envs_per_worker), 2, "ray",
                               ray_address=cluster.address)
        try:
            state = BCRLAgent.from_pretrained(policy_dir).module.state_dict()
            sps, one_step_s, _ = measure(workers, state, 2 * args.envs_per_worker, args.steps_per_env)
            actor_nodes = ray.get([a.__ray_call__.remote(lambda _: ray.get_runtime_context().get_node_id())
                                   for a in workers.actors])
            nodes = {n["NodeID"]: n for n in ray.nodes()}
        finally:
            workers.close()
    print(json.dumps({"bench": "rollout_throughput_ray_cluster", "nodes": len(nodes),
                      "node_addresses": sorted({n["NodeManagerAddress"] for n in nodes.values()}),
                      "actor_nodes": [sorted(nodes).index(node) for node in actor_nodes], "workers": 2,
                      "envs_per_worker": args.envs_per_worker, "steps_per_env": args.steps_per_env,
                      "steps_per_s": round(sps, 1), "one_step_collect_ms": round(1000 * one_step_s, 1)}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps_per_env", type=int, default=200)
    parser.add_argument("--envs_per_worker", type=int, default=1)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--ray_cluster", action="store_true", help="the two-node cluster check instead")
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        policy_dir = build_policy_dir(Path(tmp), None)
        (ray_cluster if args.ray_cluster else backends)(args, policy_dir)


if __name__ == "__main__":
    main()
