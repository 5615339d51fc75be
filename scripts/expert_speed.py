"""How soon the scripted expert can lift: the expert as it is, or with its timing knobs changed, on fresh seeds.

A bound on what a return target asks: the sparse reward pays 2.25 a step once the cube is up, so a mean return of
R at 100 % success needs a lift by step ~200 - R / 2.25. The seeds start at 3,000,000 (apart from the
demonstrations', validation's and test's); no noise. Prints one JSON line: success, mean steps to lift, mean return.
    .venv/bin/python scripts/expert_speed.py --episodes=50 --close_steps=3 --position_gain=4 --hover_height_m=0.04
"""

import argparse
import json

import numpy as np

from dataset_tools.experts import ScriptedLiftExpert
from dataset_tools.noise import DemonstratorConfig, DemonstratorNoise
from dataset_tools.record import record_episode
from lerobot_bcrl.envs import controller
from lerobot_bcrl.envs.lift import LiftEnv
from lerobot_bcrl.rl.ppo import ANALYSIS_SEED_OFFSET


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    defaults = ScriptedLiftExpert()
    for knob in ("close_steps", "position_gain", "hover_height_m"):
        parser.add_argument(f"--{knob}", type=type(getattr(defaults, knob)), default=getattr(defaults, knob))
    args = parser.parse_args()
    expert = ScriptedLiftExpert(close_steps=args.close_steps, position_gain=args.position_gain,
                                hover_height_m=args.hover_height_m)
    env, no_noise = LiftEnv(obs_type="agent_pos"), DemonstratorConfig(noise_std=0.0)
    episodes = [record_episode(env, expert, DemonstratorNoise(no_noise, controller.CONTROLLER_ACTION_DIM, i),
                               ANALYSIS_SEED_OFFSET + i)[1] for i in range(args.episodes)]
    lifts = [e["steps_to_lift"] for e in episodes if e["success"]]
    print(json.dumps({"close_steps": args.close_steps, "position_gain": args.position_gain,
                      "hover_height_m": args.hover_height_m, "episodes": args.episodes,
                      "success": float(np.mean([e["success"] for e in episodes])),
                      "steps_to_lift": float(np.mean(lifts)) if lifts else None,
                      "return": float(np.mean([e["episode_return"] for e in episodes]))}))


if __name__ == "__main__":
    main()
