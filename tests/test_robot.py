"""Kinematics on Rethink's URDF (pybullet) against robosuite's MuJoCo Sawyer, and the delta-action command
path driving the MuJoCo arm: commanded deltas are reached, limits hold (IK's memory: bench/convert_speed.py)."""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest

from lerobot_bcrl import geometry as G
from lerobot_bcrl.robot.command import CommandConfig, DeltaActionCommander
from lerobot_bcrl.robot.kinematics import KinematicsError, UrdfKinematics
from lerobot_bcrl.robot.mujoco_sawyer import MujocoSawyer
from lerobot_bcrl.robot.sim_rig import sawyer_kinematics
from lerobot_bcrl.robot.transport import GuardedCommandPath, MujocoSawyerTransport

URDF = Path("/work/shared/robots/sawyer/sawyer.urdf")
# robosuite's Lift start pose of the arm (its init_qpos), a realistic place to start commanding from
START_QPOS = np.array([0.0, -1.18, 0.0, 2.18, 0.0, 0.57, 3.3161])


@pytest.fixture(scope="module")
def kin():
    with sawyer_kinematics(URDF) as k:
        yield k


@pytest.fixture(scope="module")
def mj():
    from lerobot_bcrl.envs.lift import LiftEnv

    env = LiftEnv(obs_type="agent_pos")
    model = env.sim_env.sim.model._model
    yield model
    env.close()


def mujoco_pose(model, q):
    data = mujoco.MjData(model)
    sawyer = MujocoSawyer(model)
    data.qpos[sawyer.arm_qpos_adr] = q
    mujoco.mj_kinematics(model, data)
    return sawyer.grip_site_pose_base(data)


def test_fk_agrees_with_mujoco_sawyer(kin, mj):
    """Base frames coincide; the grip site is a fixed offset from right_hand. Measured: <= 0.6 mm, 1e-5 rad."""
    rng = np.random.default_rng(0)
    for _ in range(8):
        q = rng.uniform(kin.joint_lower_rad, kin.joint_upper_rad) * 0.8
        pos, quat = kin.forward(q)
        mj_pos, mj_quat = mujoco_pose(mj, q)
        assert np.linalg.norm(pos - mj_pos) < 1e-3
        assert G.quat_angle(G.quat_multiply(quat, G.quat_conjugate(mj_quat))) < 1e-4


def test_ik_round_trip_and_errors(kin):
    rng = np.random.default_rng(1)
    for _ in range(10):
        q_goal = START_QPOS + rng.normal(0, 0.3, 7)
        pos, quat = kin.forward(q_goal)
        q = kin.inverse(pos, quat, seed_joint_pos_rad=q_goal + rng.normal(0, 0.05, 7))
        got_pos, got_quat = kin.forward(q)
        assert np.linalg.norm(got_pos - pos) < 1e-4
        assert G.quat_angle(G.quat_multiply(got_quat, G.quat_conjugate(quat))) < 1e-3
        assert np.all(q >= kin.joint_lower_rad) and np.all(q <= kin.joint_upper_rad)
    with pytest.raises(KinematicsError, match="not in the URDF"):
        UrdfKinematics(URDF, joint_names=["right_j0", "nope"])


def test_commanded_deltas_are_reached_in_mujoco(kin, mj):
    """Each 30 Hz period commands a delta (~1 cm, up to pi/40) and measures what MuJoCo's arm did."""
    data = mujoco.MjData(mj)
    transport = MujocoSawyerTransport(mj, data)
    data.qpos[transport.sawyer.arm_qpos_adr] = START_QPOS
    mujoco.mj_kinematics(mj, data)
    path = GuardedCommandPath(DeltaActionCommander(kin, CommandConfig(fps=30)), transport)
    pos_err, rot_err = [], []
    for t in range(40):
        phase = 2 * math.pi * t / 40
        delta_pos = 0.01 * np.array([math.cos(phase), math.sin(phase), 0.3 * math.sin(2 * phase)])
        delta_quat = G.rotvec_to_quat(np.array([0.0, 0.5, 1.0]) / math.sqrt(1.25) * (math.pi / 40) * math.sin(phase))
        action = np.concatenate([delta_pos, G.quat_canonical(delta_quat), [1.0 if t > 20 else -1.0]])
        before_pos, before_quat = transport.tool_pose_base()
        command = path.step(action)
        after_pos, after_quat = transport.tool_pose_base()
        pos_err.append(np.linalg.norm((after_pos - before_pos) - delta_pos))
        achieved = G.quat_multiply(after_quat, G.quat_conjugate(before_quat))
        rot_err.append(G.quat_angle(G.quat_multiply(achieved, G.quat_conjugate(delta_quat))))
        assert not command.velocity_limited and command.stopped_because is None
    assert transport.gripper_closed and path.stops == 0
    # Stated tolerance: 1 mm and 0.01 rad per step (measured 0.017 mm, < 1e-5 rad)
    print(f"max error per step: {max(pos_err) * 1e3:.3f} mm, {max(rot_err):.5f} rad")
    assert max(pos_err) < 1e-3, max(pos_err)
    assert max(rot_err) < 0.01, max(rot_err)


class NaNJoints(MujocoSawyerTransport):
    def read_joint_positions(self):
        return np.full(7, np.nan)


def test_the_watchdog_stops_the_arm_for_a_late_or_non_finite_period(kin, mj):
    """A late action (after one period), a NaN action and NaN joint readings each give one zero-velocity period
    with the gripper held at its last command; the periods around them move the arm as commanded."""
    data = mujoco.MjData(mj)
    transport = MujocoSawyerTransport(mj, data)
    data.qpos[transport.sawyer.arm_qpos_adr] = START_QPOS
    mujoco.mj_kinematics(mj, data)
    now = [100.0]
    path = GuardedCommandPath(DeltaActionCommander(kin, CommandConfig(fps=20)), transport, clock=lambda: now[0])
    close_and_lift = np.array([0.0, 0.0, 0.01, 0.0, 0.0, 0.0, 1.0, 1.0])
    open_and_lower = np.array([0.0, 0.0, -0.01, 0.0, 0.0, 0.0, 1.0, -1.0])

    def moved(action, observed_at_s):
        before = transport.tool_pose_base()[0]
        command = path.step(action, observed_at_s)
        return command, np.linalg.norm(transport.tool_pose_base()[0] - before)

    command, distance = moved(close_and_lift, now[0] - 0.049)  # 49 ms after the observation: on time at 20 Hz
    assert command.stopped_because is None and distance > 0.009 and transport.gripper_closed
    command, distance = moved(open_and_lower, now[0] - 0.051)
    assert "ms after its deadline" in command.stopped_because and distance == 0 and transport.gripper_closed
    command, distance = moved(np.full(8, np.nan), now[0])
    assert "the action is not finite" in command.stopped_because and distance == 0
    path.transport = NaNJoints(mj, data)  # the same arm, its joint states read as NaN
    command, distance = moved(close_and_lift, now[0])
    assert "joint positions read are not finite" in command.stopped_because and distance == 0
    assert path.transport.gripper_closed  # still the last command's
    path.transport = transport
    command, distance = moved(open_and_lower, now[0])
    assert command.stopped_because is None and distance > 0.009 and not transport.gripper_closed
    assert path.stops == 3


def test_clamps_and_velocity_limits(kin):
    commander = DeltaActionCommander(kin, CommandConfig(fps=30))
    huge = np.array([0.3, 0.0, -0.3, *G.rotvec_to_quat(np.array([0.0, 0.0, 1.0])), -1.0])
    command = commander.command(huge, START_QPOS)
    assert command.action_clamped and command.velocity_limited
    assert np.all(np.abs(command.joint_vel_rad_s) <= kin.joint_max_vel_rad_s + 1e-9)
    start_pos, _ = kin.forward(START_QPOS)
    assert np.linalg.norm(command.target_pos_base_m - start_pos) == pytest.approx(G.MAX_DELTA_POS_M)
    near_limit = START_QPOS.copy()
    near_limit[0] = kin.joint_upper_rad[0] - 0.001
    command = commander.command(np.array([0, 0.05, 0, 0, 0, 0, 1, -1.0]), near_limit)
    assert np.all(command.target_joint_pos_rad <= commander.joint_upper_rad + 1e-12)
