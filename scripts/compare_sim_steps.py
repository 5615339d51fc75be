"""Record the same episodes with both simulation steps and compare them state by state.

Runs a recording config's episodes (its expert, noise, planned misses and seeds) once with robosuite's env.step and
once with the fast control step, and prints one JSON line: the largest |qpos|/|qvel| difference over every step of
every episode, and how many episodes differ by more than 1e-8. Use it to check the fast step on another platform.
    MUJOCO_GL=egl .venv/bin/python scripts/compare_sim_steps.py --episodes 100 [--config configs/record_lowdim_retry.yaml --sigma 0.01]
"""

from __future__ import annotations

import argparse
import json

import draccus
import numpy as np
from tqdm import tqdm

from dataset_tools import record as rec
from dataset_tools.experts import sample_miss_offset
from dataset_tools.noise import DemonstratorNoise
from lerobot_bcrl.envs import controller
from lerobot_bcrl.envs.lift import LiftEnv

SIM_STEPS = ("robosuite", "fast")


def episode_states(env: LiftEnv, cfg: rec.RecordConfig, episode_index: int) -> np.ndarray:
    """(steps, nq + nv) after every step of the recorder's episode `episode_index`."""
    demonstrators = cfg.resolved_demonstrators()
    noise = DemonstratorNoise(
        demonstrators[episode_index % len(demonstrators)], controller.CONTROLLER_ACTION_DIM, [cfg.seed, episode_index]
    )
    miss_rng = np.random.default_rng([cfg.seed, episode_index, 1])  # as the recorder draws it
    miss = None
    if miss_rng.uniform() < cfg.miss_probability:
        miss = sample_miss_offset(miss_rng, cfg.miss_height_range_m, cfg.miss_max_aside_m)
    states = []
    step = env.step

    def step_and_log(action):
        result = step(action)
        data = env.sim_env.sim.data
        states.append(np.concatenate([data.qpos, data.qvel]))
        return result

    env.step = step_and_log
    try:
        rec.record_episode(env, rec.make_expert(cfg), noise, cfg.seed + episode_index, miss)
    finally:
        env.step = step
    return np.stack(states)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/record_lowdim_retry.yaml")
    parser.add_argument("--sigma", type=float, default=0.01)
    parser.add_argument("--episodes", type=int, default=100)
    args = parser.parse_args()
    cfg = draccus.parse(
        rec.RecordConfig, config_path=args.config, args=[f"--sigma={args.sigma}", "--repo_id=local/unused", "--images=false"]
    )
    envs = {s: LiftEnv(obs_type="agent_pos", horizon=cfg.episode_length, sim_step=s) for s in SIM_STEPS}
    worst = []
    for episode_index in tqdm(range(args.episodes), desc="episodes", unit="ep"):
        reference, fast = (episode_states(envs[s], cfg, episode_index) for s in SIM_STEPS)
        worst.append(float(np.abs(reference - fast).max()))
    for env in envs.values():
        env.close()
    print(json.dumps({
        "bench": "compare_sim_steps", "config": args.config, "sigma": args.sigma, "episodes": args.episodes,
        "max_abs_state_difference": max(worst), "episodes_over_1e-8": sum(w > 1e-8 for w in worst),
        "bitwise_identical_episodes": sum(w == 0.0 for w in worst),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
