"""Why a Lift policy fails: roll a checkpoint out on the held-out evaluation seeds and print, per episode,
when the gripper first closed, where the cube was relative to the end effector then and how far the fingers
were turned from the nearest cube face (yaw), how close the end effector got, how high the cube went, how far
the end effector rose after the first closing (a stall or a slip), whether the fingers end closed on nothing,
how many times the gripper closed (a retry is a second closing), and for a lifted cube whether it was lost
again (the first step it was not lifted after the lift, the first step the gripper was commanded open after
it); optionally with sampled actions (position and/or gripper) instead of the mean / argmax, to compare the
policy PPO optimises with the one lerobot-eval runs; `--align_yaw` probes a policy with the demonstrators'
yaw alignment in place of its own rotation before the grasp.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 .venv/bin/python scripts/diagnose_lift_episodes.py \
        --checkpoint=outputs/.../pretrained_model --episodes=20 --modes=mean,sampled_position,sampled_both
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from dataset_tools.experts import fingers_closed_on_nothing
from lerobot_bcrl.envs.lift import LiftEnv
from lerobot_bcrl import geometry
from lerobot_bcrl.features import ENV_STATE_CUBE_QUAT, STATE_EEF_POS, STATE_EEF_QUAT, STATE_GRIPPER_QPOS
from lerobot_bcrl.rl.agent import BCRLAgent, flatten_observation
from lerobot_bcrl.rl.ppo import EVAL_SEED_OFFSET
from lerobot_bcrl.rl.rollout import EpisodeStats

MODES = {  # (sample delta_pos and rotation, sample the gripper)
    "mean": (False, False),
    "sampled_gripper": (False, True),
    "sampled_position": (True, False),
    "sampled_both": (True, True),
}


def yaw_error(obs: dict) -> float:
    """The turn (rad) from the fingers to the nearest cube face, as the scripted demonstrators compute it."""
    return geometry.cube_yaw_error(obs["agent_pos"][STATE_EEF_QUAT], obs["environment_state"][ENV_STATE_CUBE_QUAT])


def episode(agent: BCRLAgent, env: LiftEnv, seed: int, sample_position: bool, sample_gripper: bool,
            align_yaw: bool = False) -> dict:
    policy = agent.policy
    obs, _ = env.reset(seed=seed)
    cube_start_z = float(obs["environment_state"][2])
    stats = EpisodeStats(0.0, 0, False, None, seed=seed)  # return, first lift and lifted steps, as evaluations count them
    closed_at, cube_minus_eef_at_close, min_distance, max_cube_rise = None, None, np.inf, -np.inf
    yaw_error_at_close = None  # fingers against the nearest cube face (the demonstrators turn to it first)
    grasp_attempts, was_closed = 0, False  # closings of the gripper (a retry after a miss is a second one)
    eef_z_at_close, max_eef_rise_after_close = None, None  # a stall (closed, not rising) or a slip (rose without it)
    dropped_at, opened_after_lift_at = None, None  # a cube lost after the lift: let go, or slipped
    for t in range(env.horizon):
        batch = agent.observation_batch({k: v[None] for k, v in flatten_observation(obs).items()})
        with torch.no_grad():
            outputs = policy.model(batch)
            continuous_dist, gripper_dist = policy.action_distributions(outputs)
            continuous = continuous_dist.sample() if sample_position else continuous_dist.mean
            gripper = gripper_dist.sample() if sample_gripper else outputs.gripper_logits.argmax(-1)
            action = policy.to_env_action(continuous, gripper)[0].numpy()
        if align_yaw and closed_at is None:  # a probe: the demonstrators' turn to the nearest face, until the first closing
            action[3:7] = geometry.rotvec_to_quat(np.array([0.0, 0.0, yaw_error(obs)]))  # the env clamps it to pi/40 per step
        obs, reward, _, _, info = env.step(action)
        stats.record_step(reward, info)
        cube_minus_eef = obs["environment_state"][7:10]
        min_distance = min(min_distance, float(np.linalg.norm(cube_minus_eef)))
        max_cube_rise = max(max_cube_rise, float(obs["environment_state"][2]) - cube_start_z)
        eef_z = float(obs["agent_pos"][STATE_EEF_POS][2])
        if action[7] > 0 and closed_at is None:
            closed_at, cube_minus_eef_at_close = t, [round(float(x), 3) for x in cube_minus_eef]
            yaw_error_at_close = yaw_error(obs)
            eef_z_at_close, max_eef_rise_after_close = eef_z, 0.0
        if eef_z_at_close is not None:
            max_eef_rise_after_close = max(max_eef_rise_after_close, eef_z - eef_z_at_close)
        grasp_attempts += int(action[7] > 0 and not was_closed)
        was_closed = bool(action[7] > 0)
        if stats.success and not info["is_success"] and dropped_at is None:
            dropped_at = t
        if stats.success and action[7] <= 0 and opened_after_lift_at is None:
            opened_after_lift_at = t
    return {"seed": seed, "success": stats.success, "return": stats.episode_return,
            "lifted_at": None if stats.steps_to_lift is None else stats.steps_to_lift - 1, "lifted_steps": stats.lifted_steps,
            "dropped_at": dropped_at, "gripper_opened_after_lift_at": opened_after_lift_at, "gripper_closed_at": closed_at,
            "cube_minus_eef_at_close_m": cube_minus_eef_at_close,
            "yaw_error_at_close_deg": None if yaw_error_at_close is None else round(float(np.degrees(yaw_error_at_close)), 1),
            "min_eef_cube_distance_m": round(min_distance, 3),
            "max_cube_rise_m": round(max_cube_rise, 3), "grasp_attempts": grasp_attempts,
            "max_eef_rise_after_close_m": None if max_eef_rise_after_close is None else round(max_eef_rise_after_close, 3),
            "fingers_closed_on_nothing_at_end": fingers_closed_on_nothing(obs["agent_pos"][STATE_GRIPPER_QPOS])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True, help="a pretrained_model directory of a bcrl policy")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--modes", default="mean", help=f"comma-separated, from {list(MODES)}")
    parser.add_argument("--quiet", action="store_true", help="only the success rate per mode")
    parser.add_argument("--align_yaw", action="store_true",
                        help="probe: replace the policy's rotation by the turn to the nearest cube face until the first closing")
    args = parser.parse_args()
    agent = BCRLAgent.from_pretrained(args.checkpoint)
    env = LiftEnv(obs_type="agent_pos")
    for mode in args.modes.split(","):
        torch.manual_seed(0)
        results = [episode(agent, env, EVAL_SEED_OFFSET + i, *MODES[mode], align_yaw=args.align_yaw)
                   for i in range(args.episodes)]
        if not args.quiet:
            for result in results:
                print(json.dumps({"mode": mode, **result}))
        print(json.dumps({"mode": mode, "align_yaw": args.align_yaw, "episodes": len(results),
                          "return": float(np.mean([r["return"] for r in results])),
                          "success": float(np.mean([r["success"] for r in results])),
                          "episodes_with_a_retry": sum(r["grasp_attempts"] > 1 for r in results),
                          "successes_after_a_retry": sum(r["grasp_attempts"] > 1 and r["success"] for r in results),
                          "lifted_then_dropped": sum(r["dropped_at"] is not None for r in results),
                          "mean_abs_yaw_error_at_close_deg": float(np.mean([abs(r["yaw_error_at_close_deg"]) for r in results
                                                                           if r["yaw_error_at_close_deg"] is not None])),
                          "dropped_after_opening": sum(r["dropped_at"] is not None and r["gripper_opened_after_lift_at"] is not None
                                                       and r["gripper_opened_after_lift_at"] <= r["dropped_at"] for r in results)}))


if __name__ == "__main__":
    main()
