"""The hardware boundary of the command path: read joints, send joint velocities and the gripper, keep time; and
the watchdog between the policy and it (`GuardedCommandPath`).

A real rig implements `JointVelocityTransport` in a few lines (Intera: `limb.joint_angles()`,
`limb.set_joint_velocities()`, `limb.set_command_timeout()`, `gripper.close()`, a `rospy.Rate`); tests use
`MujocoSawyerTransport`.
"""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from lerobot_bcrl.robot.command import DeltaActionCommander, JointCommand


class JointVelocityTransport(Protocol):
    """What a rig implements. `send` holds for one control period: a real transport must also stop the arm by itself
    when no command comes for longer (Intera: `limb.set_command_timeout`), which covers a policy that never answers."""

    def read_joint_positions(self) -> np.ndarray: ...

    def send(self, joint_vel_rad_s: np.ndarray, gripper_closed: bool) -> None: ...

    def wait_period(self, period_s: float) -> None:
        """Return at the start of the next control period (a real rig sleeps; a simulator integrates)."""
        ...


class GuardedCommandPath:
    """One control period per `step`: read the joints, turn the action into joint velocities, send, wait. The
    watchdog: in a period where the action came after its deadline (one period after the observation it answers),
    or where the action, the joints read or the IK's solution are not finite, the arm is sent zero joint velocities
    and the gripper its last command (open before the first); the step says why, and `stops` counts such periods."""

    def __init__(
        self,
        commander: DeltaActionCommander,
        transport: JointVelocityTransport,
        clock=time.monotonic,
        period_s: float | None = None,
    ):
        """`period_s`: how long each command holds; the commander's (the dataset's) period unless a study of rate
        mismatch sets another (the commander still scales velocities for its own fps)."""
        self.commander, self.transport, self.clock = commander, transport, clock
        self.period_s = period_s if period_s is not None else 1.0 / commander.cfg.fps
        self.gripper_closed = False  # the last command sent
        self.stops = 0

    def reset(self) -> None:
        """A new episode: the gripper's last command is open again (what a stop holds before the first command)."""
        self.gripper_closed = False

    def step(self, action: np.ndarray, observed_at_s: float | None = None) -> JointCommand:
        """`observed_at_s`: the `clock()` time of the observation the action answers (None: no deadline)."""
        action = np.asarray(action, dtype=np.float64)
        joint_pos_rad = np.asarray(self.transport.read_joint_positions(), dtype=np.float64)
        late_s = None if observed_at_s is None else self.clock() - observed_at_s - self.period_s
        if late_s is not None and late_s > 0:
            command = self._stop(joint_pos_rad, f"the action came {1000 * late_s:.1f} ms after its deadline")
        elif not np.all(np.isfinite(action)):
            command = self._stop(joint_pos_rad, f"the action is not finite: {action.tolist()}")
        elif not np.all(np.isfinite(joint_pos_rad)):
            command = self._stop(joint_pos_rad, f"the joint positions read are not finite: {joint_pos_rad.tolist()}")
        else:
            command = self.commander.command(action, joint_pos_rad)
            if not np.all(np.isfinite(command.target_joint_pos_rad)):
                command = self._stop(joint_pos_rad, f"the IK's solution is not finite: {command.target_joint_pos_rad}")
        self.gripper_closed = command.gripper_closed
        self.transport.send(command.joint_vel_rad_s, command.gripper_closed)
        self.transport.wait_period(self.period_s)
        return command

    def _stop(self, joint_pos_rad: np.ndarray, reason: str) -> JointCommand:
        self.stops += 1
        nan3, nan4 = np.full(3, np.nan), np.full(4, np.nan)
        return JointCommand(np.zeros_like(joint_pos_rad), joint_pos_rad, nan3, nan4, self.gripper_closed,
                            action_clamped=False, velocity_limited=False, stopped_because=reason)


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
