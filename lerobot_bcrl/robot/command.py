"""The real-robot command path: a policy's 8-D delta action -> clamped target pose -> joint targets by IK
on the URDF -> proportional joint-velocity commands at the dataset's fps, within joint and velocity limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_bcrl.geometry import GRIPPER_CLOSED, apply_delta_action, make_delta_action
from lerobot_bcrl.robot.kinematics import UrdfKinematics


@dataclass
class CommandConfig:
    fps: float = 30.0  # must be the dataset's fps: one action per control period
    gain: float = 1.0  # fraction of the joint error commanded per period (1: reach it in one period)
    velocity_limit_fraction: float = 1.0  # of the URDF's joint velocity limits
    joint_limit_margin_rad: float = 0.01  # stay this far inside the URDF's joint limits


@dataclass
class JointCommand:
    joint_vel_rad_s: np.ndarray  # (n,) what the transport sends for one period
    target_joint_pos_rad: np.ndarray  # (n,) the IK solution
    target_pos_base_m: np.ndarray
    target_quat_base_xyzw: np.ndarray
    gripper_closed: bool
    action_clamped: bool
    velocity_limited: bool
    stopped_because: str | None = None  # the watchdog's reason for a zero-velocity period (transport.py)


class DeltaActionCommander:
    """Turns one action into one period's joint-velocity command, from the measured joint positions."""

    def __init__(self, kinematics: UrdfKinematics, cfg: CommandConfig | None = None):
        self.kinematics = kinematics
        self.cfg = cfg or CommandConfig()
        margin = self.cfg.joint_limit_margin_rad
        self.joint_lower_rad = kinematics.joint_lower_rad + margin
        self.joint_upper_rad = kinematics.joint_upper_rad - margin
        self.max_joint_vel_rad_s = kinematics.joint_max_vel_rad_s * self.cfg.velocity_limit_fraction

    def command(self, action: np.ndarray, joint_pos_rad: np.ndarray) -> JointCommand:
        action = np.asarray(action, dtype=np.float64)
        joint_pos_rad = np.asarray(joint_pos_rad, dtype=np.float64)
        # The same clamps as the datasets: a policy cannot ask for more than the demos could show.
        action, clamped = make_delta_action(action[:3], action[3:7], action[7])
        pos_m, quat_xyzw = self.kinematics.forward(joint_pos_rad)
        target_pos, target_quat = apply_delta_action(pos_m, quat_xyzw, action)
        target_joint = np.clip(
            self.kinematics.inverse(target_pos, target_quat, joint_pos_rad), self.joint_lower_rad, self.joint_upper_rad
        )
        joint_vel = self.cfg.gain * self.cfg.fps * (target_joint - joint_pos_rad)
        # Scale the whole vector, not each joint, so that the tool keeps its direction when limited.
        ratio = float(np.max(np.abs(joint_vel) / self.max_joint_vel_rad_s))
        limited = ratio > 1.0
        if limited:
            joint_vel = joint_vel / ratio
        return JointCommand(joint_vel, target_joint, target_pos, target_quat, bool(action[7] >= GRIPPER_CLOSED), clamped, limited)
