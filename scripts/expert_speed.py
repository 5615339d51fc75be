"""How soon the scripted expert (with its timing knobs) or a policy closes the gripper and lifts, on fresh seeds.

A bound on what a return target asks: the sparse reward pays 2.25 a step once the cube is up, so a mean return of
R at 100 % success needs a lift by step ~200 - R / 2.25. The seeds start at 3,000,000 (apart from the
demonstrations', validation's and test's); no noise; a policy acts through `bcrl-record`'s path for a learned expert.
Prints one JSON line: success, mean return and, over the lifted episodes, the mean step of the first command to
close the gripper and of the lift.
    .venv/bin/python scripts/expert_speed.py --episodes=50 --close_steps=3 --position_gain=4 --hover_height_m=0.04
    .venv/bin/python scripts/expert_speed.py --episodes=50 --policy=<run>/checkpoints/best/pretrained_model
"""

import argparse
import json

import numpy as np

from dataset_tools.experts import PolicyExpert, ScriptedLiftExpert
from dataset_tools.noise import DemonstratorConfig, DemonstratorNoise
from dataset_tools.record import record_episode
from lerobot_bcrl import features as F
from lerobot_bcrl.envs import controller
from lerobot_bcrl.envs.lift import LiftEnv
from lerobot_bcrl.geometry import GRIPPER_CLOSED, gripper_class
from lerobot_bcrl.rl.ppo import ANALYSIS_SEED_OFFSET

KNOBS = ("close_steps", "position_gain", "hover_height_m")  # the scripted expert's timing, settable here


def first_close_step(frames: dict) -> int | None:
    """The first step whose action commands the gripper closed (None where none does)."""
    closing = np.array([gripper_class(g) == GRIPPER_CLOSED for g in frames[F.ACTION_KEY][:, -1]])
    return int(np.argmax(closing)) if closing.any() else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--policy", default=None, help="a pretrained_model folder to time instead of the expert")
    defaults = ScriptedLiftExpert()
    for knob in KNOBS:
        parser.add_argument(f"--{knob}", type=type(getattr(defaults, knob)), default=getattr(defaults, knob))
    args = parser.parse_args()
    knobs = {k: getattr(args, k) for k in KNOBS}
    expert = PolicyExpert(args.policy) if args.policy else ScriptedLiftExpert(**knobs)
    env = LiftEnv(obs_type=expert.obs_type if args.policy else "agent_pos")
    no_noise = DemonstratorConfig(noise_std=0.0)
    episodes = []
    for i in range(args.episodes):
        frames, stats = record_episode(env, expert, DemonstratorNoise(no_noise, controller.CONTROLLER_ACTION_DIM, i),
                                       ANALYSIS_SEED_OFFSET + i)
        episodes.append(stats | {"first_close_step": first_close_step(frames)})
    lifted = [e for e in episodes if e["success"]]

    def mean_step(key: str) -> float | None:  # over the lifted episodes
        return float(np.mean([e[key] for e in lifted])) if lifted else None

    who = {"policy": args.policy} if args.policy else knobs
    print(json.dumps(who | {"episodes": args.episodes, "success": float(np.mean([e["success"] for e in episodes])),
                            "first_close_step": mean_step("first_close_step"),
                            "steps_to_lift": mean_step("steps_to_lift"),
                            "return": float(np.mean([e["episode_return"] for e in episodes]))}))


if __name__ == "__main__":
    main()
