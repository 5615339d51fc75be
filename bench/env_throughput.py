"""Env steps/s of our Lift wrapper against raw robosuite (same run), and the raw MuJoCo ceiling.

Prints one JSON line. Targets (issue 2): wrapper overhead <= 5 % low-dim; with the camera >= 2x
robosuite's own camera-observation path at 128x128.
    python bench/env_throughput.py [--steps 400]
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import robosuite  # noqa: E402

from lerobot_bcrl.envs.lift import LiftEnv  # noqa: E402

ZERO_DELTA_ACTION = np.array([0, 0, 0, 0, 0, 0, 1.0, -1.0])
ZERO_CONTROLLER_ACTION = np.array([0, 0, 0, 0, 0, 0, -1.0])


def _robosuite(camera: bool):
    return robosuite.make(
        "Lift",
        robots="Sawyer",
        has_renderer=False,
        has_offscreen_renderer=camera,
        use_camera_obs=camera,
        camera_names="agentview",
        camera_heights=128,
        camera_widths=128,
        reward_scale=None,
        ignore_done=True,
        hard_reset=False,
    )


def steps_per_second(step, n_steps: int, repeats: int) -> float:
    best = 0.0
    for _ in range(repeats):  # best of several: the least disturbed by the rest of the machine
        start = time.perf_counter()
        for _ in range(n_steps):
            step()
        best = max(best, n_steps / (time.perf_counter() - start))
    return best


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    result = {"bench": "env_throughput", "steps": args.steps}

    raw = _robosuite(camera=False)
    raw.reset()
    result["robosuite_lowdim_sps"] = steps_per_second(lambda: raw.step(ZERO_CONTROLLER_ACTION), args.steps, args.repeats)
    # The ceiling: MuJoCo alone, same model, same number of physics substeps per control step.
    model, data = raw.sim.model._model, mujoco.MjData(raw.sim.model._model)
    substeps = int(round(1.0 / (raw.control_freq * model.opt.timestep)))
    result["mujoco_ceiling_sps"] = steps_per_second(lambda: mujoco.mj_step(model, data, substeps), args.steps, args.repeats)
    raw.close()

    ours = LiftEnv(obs_type="agent_pos", horizon=10**9)
    ours.reset(seed=0)
    result["ours_lowdim_sps"] = steps_per_second(lambda: ours.step(ZERO_DELTA_ACTION), args.steps, args.repeats)
    ours.close()

    cam_steps = max(args.steps // 4, 20)
    raw_cam = _robosuite(camera=True)
    raw_cam.reset()
    result["robosuite_camera_sps"] = steps_per_second(lambda: raw_cam.step(ZERO_CONTROLLER_ACTION), cam_steps, args.repeats)
    raw_cam.close()
    for cheap in (False, True):
        env = LiftEnv(obs_type="pixels_agent_pos", cheap_render=cheap, horizon=10**9)
        env.reset(seed=0)
        key = "ours_camera_cheap_sps" if cheap else "ours_camera_full_sps"
        result[key] = steps_per_second(lambda: env.step(ZERO_DELTA_ACTION), cam_steps, args.repeats)
        env.close()

    result["lowdim_overhead_pct"] = 100.0 * (1.0 - result["ours_lowdim_sps"] / result["robosuite_lowdim_sps"])
    result["camera_speedup_vs_robosuite"] = result["ours_camera_cheap_sps"] / result["robosuite_camera_sps"]
    result["lowdim_fraction_of_mujoco_ceiling"] = result["ours_lowdim_sps"] / result["mujoco_ceiling_sps"]
    print(json.dumps({k: round(v, 3) if isinstance(v, float) else v for k, v in result.items()}))


if __name__ == "__main__":
    main()
