"""Resident memory of one bcrl-finetune rollout worker process with 0, 1, 2 and 8 envs (after a 200-step
rollout), against baselines measured in the same run: a spawned interpreter that imported torch (spawn re-imports
this script, and with it torch), and one that also holds a raw robosuite Lift env stepped 200 times.

Prints one JSON line, in MiB: `private` = private dirty pages, what a process costs the machine beyond the shared
libraries; `pss` shares those pages out among the processes. With them the MjModel buffer and the MjData arena
MuJoCo sizes for robosuite's Lift (the arena, from its njmax/nconmax 5000, is reserved address space: pages are
resident only where used)."""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import tempfile
from functools import partial
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from rollout_throughput import build_policy_dir  # noqa: E402


def memory_mib(pid: int) -> dict[str, float]:
    """Rss, Pss and Private_Dirty of a process, from /proc/<pid>/smaps_rollup (Linux)."""
    fields = {}
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]:
        name, value = line.split(":")
        fields[name] = int(value.split()[0]) / 1024
    return {"rss": round(fields["Rss"], 1), "pss": round(fields["Pss"], 1), "private": round(fields["Private_Dirty"], 1)}


def _baseline_process(kind: str, steps: int, queue) -> None:
    if kind == "raw_robosuite_1env":
        import numpy as np
        import robosuite

        env = robosuite.make("Lift", robots="Sawyer", has_renderer=False, has_offscreen_renderer=False,
                             use_camera_obs=False, use_object_obs=True, control_freq=20, horizon=steps,
                             ignore_done=True, hard_reset=False)
        env.reset()
        low, high = env.action_spec
        for _ in range(steps):
            env.step(np.random.uniform(low, high))
        model = env.sim.model._model  # one compiled MjModel per env: its buffer is resident, the arena reserved
        queue.put({**memory_mib(os.getpid()), "mjmodel_buffer": round(model.nbuffer / 2**20, 1),
                   "mjdata_arena_reserved": round(model.narena / 2**20, 1)})
        return
    queue.put(memory_mib(os.getpid()))


def baseline(kind: str, steps: int) -> dict[str, float]:
    context = mp.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=_baseline_process, args=(kind, steps, queue))
    process.start()
    result = queue.get()
    process.join()
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps_per_env", type=int, default=200)
    parser.add_argument("--envs_per_worker", type=int, nargs="+", default=[0, 1, 2, 8])
    args = parser.parse_args()

    import torch

    from lerobot_bcrl.envs.configuration_lift import LiftEnvConfig
    from lerobot_bcrl.rl.agent import BCRLAgent
    from lerobot_bcrl.rl.rollout import ProcessWorkers, make_gym_env

    torch.set_num_threads(1)
    result = {"bench": "worker_memory", "unit": "MiB",
              "python_torch": baseline("python_torch", args.steps_per_env),
              "raw_robosuite_1env": baseline("raw_robosuite_1env", args.steps_per_env)}
    env_cfg = LiftEnvConfig(obs_type="agent_pos")
    with tempfile.TemporaryDirectory() as tmp:
        policy_dir = build_policy_dir(Path(tmp), None)
        for n_envs in args.envs_per_worker:
            workers = ProcessWorkers([{"make_env": partial(make_gym_env, env_cfg.gym_id, env_cfg.gym_kwargs),
                                       "make_agent": partial(BCRLAgent.from_pretrained, policy_dir),
                                       "n_envs": n_envs, "seed": 0}])
            if n_envs:
                state = BCRLAgent.from_pretrained(policy_dir).state_dict()
                workers.collect(state, args.steps_per_env)
            result[f"worker_{n_envs}_envs"] = memory_mib(workers.processes[0].pid)
            workers.close()
    counts = [n for n in args.envs_per_worker if n]
    if len(counts) >= 2:  # what each further env adds once one is there
        low, high = result[f"worker_{counts[0]}_envs"], result[f"worker_{counts[-1]}_envs"]
        result["private_per_further_env"] = round((high["private"] - low["private"]) / (counts[-1] - counts[0]), 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
