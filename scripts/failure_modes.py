"""How a policy's failures look: roll a checkpoint out on Lift and describe every episode that never lifts the cube.

The seeds start at 3,000,000, apart from the demonstrations', validation's (2,000,000 + i) and test's (1,000,000 + i),
so that looking at failures chooses nothing. Prints one JSON line per failed episode (its seed; how often the policy
commanded the gripper closed; the end effector's nearest approach to the cube's centre; how far the cube slid and
rose; the distance between them at the end) and a last line with the count. Deterministic actions, as in evaluation.
An image policy sees the camera; the description reads the simulator's state either way.
    .venv/bin/python scripts/failure_modes.py --policy=<run>/checkpoints/best/pretrained_model --episodes=40
"""

import argparse
import json

import numpy as np

from lerobot_bcrl.envs.lift import LiftEnv
from lerobot_bcrl.features import ENV_STATE_CUBE_POS, ENV_STATE_EEF_TO_CUBE
from lerobot_bcrl.geometry import GRIPPER_CLOSED, gripper_class
from lerobot_bcrl.policy_runner import PolicyRunner
from lerobot_bcrl.rl.ppo import ANALYSIS_SEED_OFFSET


def describe_episode(runner: PolicyRunner, env: LiftEnv, seed: int) -> dict:
    obs, _ = env.reset(seed=seed)
    runner.reset()
    cube_start = obs["environment_state"][ENV_STATE_CUBE_POS].copy()
    closings, was_closed, nearest_m, rise_m, lifted = 0, False, np.inf, 0.0, False
    for _ in range(env.horizon):
        action = runner.delta_action(obs)
        closed = gripper_class(action[-1]) == GRIPPER_CLOSED
        closings += int(closed and not was_closed)
        was_closed = closed
        obs, _, _, _, info = env.step(action)
        state = obs["environment_state"]
        cube, eef_to_cube = state[ENV_STATE_CUBE_POS], state[ENV_STATE_EEF_TO_CUBE]
        nearest_m = min(nearest_m, float(np.linalg.norm(eef_to_cube)))
        rise_m = max(rise_m, float(cube[2] - cube_start[2]))
        lifted |= info["is_success"]
    return {"seed": seed, "lifted": lifted, "closings": closings, "nearest_cm": round(100 * nearest_m, 1),
            "cube_slid_cm": round(100 * float(np.linalg.norm(cube[:2] - cube_start[:2])), 1),
            "cube_rose_cm": round(100 * rise_m, 1),
            "final_distance_cm": round(100 * float(np.linalg.norm(eef_to_cube)), 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True, help="a pretrained_model folder")
    parser.add_argument("--episodes", type=int, default=40)
    args = parser.parse_args()
    runner = PolicyRunner(args.policy)
    env = LiftEnv(obs_type=runner.obs_type)
    failures = 0
    for i in range(args.episodes):
        episode = describe_episode(runner, env, ANALYSIS_SEED_OFFSET + i)
        if not episode.pop("lifted"):
            failures += 1
            print(json.dumps(episode))
    print(json.dumps({"policy": args.policy, "episodes": args.episodes, "failures": failures}))


if __name__ == "__main__":
    main()
