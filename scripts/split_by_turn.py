"""Results on the held-out evaluation seeds split by the sign of the turn the fingers need at reset to line up
with the nearest cube face (geometry.cube_yaw_error): return, failures and steps to lift per side, for finished
runs' `eval_final.json` files and, with `--expert_sigma`, for the scripted expert played on the same seeds.

    MUJOCO_GL=egl .venv/bin/python scripts/split_by_turn.py outputs/experiments/*/bcrl_*/eval_final.json
    MUJOCO_GL=egl .venv/bin/python scripts/split_by_turn.py --expert_sigma=0 --episodes=50
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from dataset_tools.experts import ScriptedLiftExpert
from dataset_tools.noise import DemonstratorConfig, DemonstratorNoise
from dataset_tools.record import record_episode
from lerobot_bcrl import geometry
from lerobot_bcrl.envs import controller
from lerobot_bcrl.envs.lift import LiftEnv
from lerobot_bcrl.features import ENV_STATE_CUBE_QUAT, STATE_EEF_QUAT
from lerobot_bcrl.rl.ppo import EVAL_SEED_OFFSET


def turns_at_reset(env: LiftEnv, seeds: list[int]) -> dict[int, float]:
    """Seed -> the turn (degrees) from the fingers to the nearest cube face right after reset."""
    turns = {}
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        error = geometry.cube_yaw_error(obs["agent_pos"][STATE_EEF_QUAT], obs["environment_state"][ENV_STATE_CUBE_QUAT])
        turns[seed] = math.degrees(error)
    return turns


def split(name: str, episodes: list[dict], turns: dict[int, float]) -> str:
    cells = [name]
    for side, on_side in (("turn > 0", lambda t: t > 0), ("turn <= 0", lambda t: t <= 0)):
        chosen = [e for e in episodes if on_side(turns[e["seed"]])]
        lifts = [e["steps_to_lift"] for e in chosen if e["success"]]
        cells.append(f"{side}: {len(chosen)} episodes, return {np.mean([e['episode_return'] for e in chosen]):.1f}, "
                     f"failures {sum(not e['success'] for e in chosen)}, lift {np.mean(lifts) if lifts else float('nan'):.1f}")
    return " | ".join(cells)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("eval_files", nargs="*", help="eval_final.json files of bcrl-finetune runs")
    parser.add_argument("--episodes", type=int, default=50, help="evaluation seeds EVAL_SEED_OFFSET + 0..N-1")
    parser.add_argument("--expert_sigma", type=float, default=None, help="also play the scripted expert at this sigma")
    args = parser.parse_args()

    env = LiftEnv(obs_type="agent_pos")
    seeds = list(range(EVAL_SEED_OFFSET, EVAL_SEED_OFFSET + args.episodes))
    turns = turns_at_reset(env, seeds)
    for path in args.eval_files:
        episodes = [e for e in json.load(open(path))["episodes"] if e["seed"] in turns]
        print(split(path, episodes, turns))
    if args.expert_sigma is not None:
        expert = ScriptedLiftExpert(reopen_on_empty_grasp=True)
        episodes = []
        for seed in seeds:
            noise = DemonstratorNoise(DemonstratorConfig(noise_std=args.expert_sigma), controller.CONTROLLER_ACTION_DIM, seed)
            _, stats = record_episode(env, expert, noise, seed)
            episodes.append({"seed": seed, **stats})
        print(split(f"scripted expert, sigma {args.expert_sigma:g}", episodes, turns))


if __name__ == "__main__":
    main()
