"""The hardware boundary of the command path: read joints, send joint velocities and the gripper, keep time.

A real rig implements `JointVelocityTransport` in a few lines (Intera: `limb.joint_angles()`,
`limb.set_joint_velocities()`, `gripper.close()`, a `rospy.Rate`); tests use `MujocoSawyerTransport`.
"""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from lerobot_bcrl.robot.command import DeltaActionCommander, JointCommand


class JointVelocityTransport(Protocol):
    def read_joint_positions(self) -> np.ndarray: ...

    def send(self, joint_vel_rad_s: np.ndarray, gripper_closed: bool) -> None: ...

    def wait_period(self, period_s: float) -> None:
        """Return at the start of the next control period (a real rig sleeps; a simulator integrates)."""
        ...


def step(commander: DeltaActionCommander, transport: JointVelocityTransport, action: np.ndarray) -> JointCommand:
    """One control period: read, command, send, wait."""
    command = commander.command(action, transport.read_joint_positions())
    transport.send(command.joint_vel_rad_s, command.gripper_closed)
    transport.wait_period(1.0 / commander.cfg.fps)
    return command


class WallClockRate:
    """Sleep to a fixed period (for real transports): the dataset's fps is the rate the policy runs at."""

    def __init__(self):
        self._next = None

    def wait(self, period_s: float) -> None:
        now = time.monotonic()
        self._next = (self._next or now) + period_s
        if self._next > now:
            time.sleep(self._next - now)
        else:
            self._next = now  # overran: do not try to catch up with a burst


class MujocoSawyerTransport:
    """robosuite's MuJoCo Sawyer as an ideal joint-velocity robot: each period integrates the commanded
    velocities into the joint positions (kinematics only, like a stiff low-level velocity loop)."""

    def __init__(self, model, data, substeps: int = 10):
        import mujoco

        from lerobot_bcrl.robot.mujoco_sawyer import MujocoSawyer

        self._mujoco = mujoco
        self.model, self.data = model, data
        self.sawyer = MujocoSawyer(model)
        self.substeps = substeps
        self._joint_vel = np.zeros(len(self.sawyer.arm_qpos_adr))
        self.gripper_closed = False
        self._lower = model.jnt_range[self.sawyer.arm_joint_ids, 0]
        self._upper = model.jnt_range[self.sawyer.arm_joint_ids, 1]

    def read_joint_positions(self) -> np.ndarray:
        return self.sawyer.joint_pos_rad(self.data)

    def send(self, joint_vel_rad_s: np.ndarray, gripper_closed: bool) -> None:
        self._joint_vel = np.asarray(joint_vel_rad_s, dtype=np.float64).copy()
        self.gripper_closed = gripper_closed

    def wait_period(self, period_s: float) -> None:
        dt = period_s / self.substeps
        for _ in range(self.substeps):
            q = self.data.qpos[self.sawyer.arm_qpos_adr] + self._joint_vel * dt
            self.data.qpos[self.sawyer.arm_qpos_adr] = np.clip(q, self._lower, self._upper)
        self._mujoco.mj_kinematics(self.model, self.data)

    def tool_pose_base(self) -> tuple[np.ndarray, np.ndarray]:
        return self.sawyer.grip_site_pose_base(self.data)
