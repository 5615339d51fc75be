"""The one conversion between our 8-D delta action and robosuite's OSC_POSE delta controller input.

robosuite's default Sawyer controller (OSC_POSE, input_type "delta", input_ref_frame "base") takes
`[px, py, pz, rx, ry, rz, gripper]` in [-1, 1]: position scaled by 0.05 m and an axis-angle rotation
scaled by 0.5 rad per unit. Our layout is `[dx, dy, dz, qx, qy, qz, qw, gripper]` in metres and a unit
quaternion (method.md section 1).
"""

from __future__ import annotations

import numpy as np

from lerobot_bcrl import geometry

# From robosuite/controllers/config/robots/default_sawyer.json (output_max for input 1.0).
CONTROLLER_POS_SCALE_M = 0.05
CONTROLLER_ROT_SCALE_RAD = 0.5
CONTROLLER_ACTION_DIM = 7


def delta_action_to_controller(action: np.ndarray) -> tuple[np.ndarray, bool]:
    """8-D delta action -> robosuite controller input; clamps first. Returns (controller_action, clamped)."""
    action = np.asarray(action, dtype=np.float64)
    if action.shape != (geometry.ACTION_DIM,):
        raise ValueError(f"expected an action of shape ({geometry.ACTION_DIM},), got {action.shape}")
    if not np.all(np.isfinite(action)):
        raise ValueError(f"non-finite action: {action}")
    delta_pos_m, pos_clamped = geometry.clamp_delta_pos(action[:3])
    quat = action[3:7]
    if np.linalg.norm(quat) < 1e-6:  # a policy that outputs zeros means "no rotation"
        quat = geometry.IDENTITY_QUAT_XYZW
    delta_quat_xyzw, rot_clamped = geometry.clamp_delta_quat(quat)
    rotvec_rad = geometry.quat_to_rotvec(delta_quat_xyzw)
    controller_action = np.concatenate(
        [
            delta_pos_m / CONTROLLER_POS_SCALE_M,
            rotvec_rad / CONTROLLER_ROT_SCALE_RAD,
            [geometry.gripper_class(action[7])],
        ]
    )
    return controller_action, pos_clamped or rot_clamped


def controller_to_delta_action(controller_action: np.ndarray) -> tuple[np.ndarray, bool]:
    """robosuite controller input (what an expert emits, noise included) -> clamped 8-D delta action."""
    controller_action = np.clip(np.asarray(controller_action, dtype=np.float64), -1.0, 1.0)
    delta_pos_m = controller_action[:3] * CONTROLLER_POS_SCALE_M
    delta_quat_xyzw = geometry.rotvec_to_quat(controller_action[3:6] * CONTROLLER_ROT_SCALE_RAD)
    return geometry.make_delta_action(delta_pos_m, delta_quat_xyzw, controller_action[6])
