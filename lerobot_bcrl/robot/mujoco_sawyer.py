"""robosuite's MuJoCo Sawyer seen through the URDF's frames: joint read-out, tool pose and the fixed offsets.

Rethink's URDF and robosuite's MJCF model the same arm; their base frames coincide (measured, see
tests/test_robot_kinematics.py) and robosuite's grip site is a fixed offset from the URDF's `right_hand`.
"""

from __future__ import annotations

import mujoco
import numpy as np

from lerobot_bcrl.geometry import pose_compose, pose_inverse
from lerobot_bcrl.robot.kinematics import SAWYER_ARM_JOINTS

# robosuite's `gripper0_right_grip_site` (what `robot0_eef_pos/quat_site` report) in the URDF's
# `right_hand` frame: 10.9 cm along the flange axis, -90 degrees about it (rethink_gripper.xml).
GRIP_SITE_IN_RIGHT_HAND_POS_M = (0.0, 0.0, 0.109)
GRIP_SITE_IN_RIGHT_HAND_QUAT_XYZW = (0.0, 0.0, -np.sqrt(0.5), np.sqrt(0.5))
ROBOT_PREFIX = "robot0_"
GRIP_SITE = "gripper0_right_grip_site"
FINGER_JOINTS = ("gripper0_right_l_finger_joint", "gripper0_right_r_finger_joint")


def wxyz_to_xyzw(quat_wxyz: np.ndarray) -> np.ndarray:
    quat_wxyz = np.asarray(quat_wxyz, dtype=np.float64)
    return np.concatenate([quat_wxyz[..., 1:], quat_wxyz[..., :1]], axis=-1)


class MujocoSawyer:
    """Index bookkeeping for a robosuite Sawyer inside any MuJoCo model/data pair."""

    def __init__(self, model: mujoco.MjModel):
        self.model = model
        self.arm_joint_ids = np.array([model.joint(ROBOT_PREFIX + n).id for n in SAWYER_ARM_JOINTS])
        self.arm_qpos_adr = np.array([model.joint(ROBOT_PREFIX + n).qposadr[0] for n in SAWYER_ARM_JOINTS])
        self.arm_dof_adr = np.array([model.joint(ROBOT_PREFIX + n).dofadr[0] for n in SAWYER_ARM_JOINTS])
        self.finger_qpos_adr = np.array([model.joint(n).qposadr[0] for n in FINGER_JOINTS])
        self.base_body = model.body(ROBOT_PREFIX + "base").id
        self.grip_site = model.site(GRIP_SITE).id

    def joint_pos_rad(self, data: mujoco.MjData) -> np.ndarray:
        return data.qpos[self.arm_qpos_adr].copy()

    def finger_pos_m(self, data: mujoco.MjData) -> np.ndarray:
        return data.qpos[self.finger_qpos_adr].copy()

    def grip_site_pose_base(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """Grip-site pose in the robot base frame (kinematics of `data` must be current)."""
        site_quat_wxyz = np.empty(4)
        mujoco.mju_mat2Quat(site_quat_wxyz, data.site_xmat[self.grip_site])
        base_inv_pos, base_inv_quat = pose_inverse(
            data.xpos[self.base_body], wxyz_to_xyzw(data.xquat[self.base_body])
        )
        return pose_compose(base_inv_pos, base_inv_quat, data.site_xpos[self.grip_site], wxyz_to_xyzw(site_quat_wxyz))
