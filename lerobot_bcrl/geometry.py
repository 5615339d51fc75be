"""Poses, quaternions and the 8-D delta action: the one place for this maths.

Quaternions are unit, in (x, y, z, w) order (robosuite's and ROS's convention). Every function takes
and returns float64 numpy arrays, batched over leading dimensions where that is natural.
"""

from __future__ import annotations

import math

import numpy as np

# The action layout shared by every dataset and policy of this project.
ACTION_NAMES = ["dx", "dy", "dz", "qx", "qy", "qz", "qw", "gripper"]
ACTION_DIM = len(ACTION_NAMES)

# The paper's feasible ranges for one control step.
MAX_DELTA_POS_M = 0.05
MAX_DELTA_ROT_RAD = math.pi / 40

GRIPPER_OPEN = -1.0
GRIPPER_CLOSED = 1.0

IDENTITY_QUAT_XYZW = np.array([0.0, 0.0, 0.0, 1.0])


def quat_normalize(quat_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternion; raises on zero-norm or non-finite input (a silent NaN would poison a dataset)."""
    quat_xyzw = np.asarray(quat_xyzw, dtype=np.float64)
    norm = np.linalg.norm(quat_xyzw, axis=-1, keepdims=True)
    if not np.all(np.isfinite(norm)) or np.any(norm < 1e-12):
        raise ValueError(f"quaternion with zero or non-finite norm: {quat_xyzw}")
    return quat_xyzw / norm


def quat_conjugate(quat_xyzw: np.ndarray) -> np.ndarray:
    quat_xyzw = np.asarray(quat_xyzw, dtype=np.float64)
    return np.concatenate([-quat_xyzw[..., :3], quat_xyzw[..., 3:]], axis=-1)


def quat_multiply(q1_xyzw: np.ndarray, q2_xyzw: np.ndarray) -> np.ndarray:
    """Hamilton product q1 * q2 (apply q2 first, then q1)."""
    x1, y1, z1, w1 = np.moveaxis(np.asarray(q1_xyzw, dtype=np.float64), -1, 0)
    x2, y2, z2, w2 = np.moveaxis(np.asarray(q2_xyzw, dtype=np.float64), -1, 0)
    return np.stack(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ],
        axis=-1,
    )


def quat_canonical(quat_xyzw: np.ndarray) -> np.ndarray:
    """Pick the cover with w >= 0, so that consecutive small deltas never flip sign."""
    quat_xyzw = np.asarray(quat_xyzw, dtype=np.float64)
    sign = np.where(quat_xyzw[..., 3:4] < 0, -1.0, 1.0)
    return quat_xyzw * sign


def quat_to_rotvec(quat_xyzw: np.ndarray) -> np.ndarray:
    """Axis-angle vector (radians) of a unit quaternion, angle in [0, pi]."""
    quat_xyzw = quat_canonical(quat_normalize(quat_xyzw))
    xyz, w = quat_xyzw[..., :3], np.clip(quat_xyzw[..., 3], -1.0, 1.0)
    sin_half = np.linalg.norm(xyz, axis=-1)
    angle = 2.0 * np.arctan2(sin_half, w)
    # angle / sin(angle / 2) -> 2 as the angle goes to 0
    scale = np.where(sin_half > 1e-9, angle / np.maximum(sin_half, 1e-12), 2.0)
    return xyz * scale[..., None]


def rotvec_to_quat(rotvec_rad: np.ndarray) -> np.ndarray:
    rotvec_rad = np.asarray(rotvec_rad, dtype=np.float64)
    angle = np.linalg.norm(rotvec_rad, axis=-1, keepdims=True)
    half = angle / 2.0
    # sin(angle/2)/angle -> 1/2 as the angle goes to 0
    scale = np.where(angle > 1e-9, np.sin(half) / np.maximum(angle, 1e-12), 0.5)
    return np.concatenate([rotvec_rad * scale, np.cos(half)], axis=-1)


def quat_angle(quat_xyzw: np.ndarray) -> np.ndarray:
    """Rotation angle in [0, pi] of a unit quaternion (either cover)."""
    w = np.abs(np.clip(quat_normalize(quat_xyzw)[..., 3], -1.0, 1.0))
    return 2.0 * np.arccos(np.minimum(w, 1.0))


def yaw_of(quat_xyzw: np.ndarray) -> float:
    """Heading of the body's x axis projected on the world xy plane (rad)."""
    x, y, z, w = quat_normalize(quat_xyzw)
    return float(np.arctan2(2 * (x * y + z * w), 1 - 2 * (y * y + z * z)))


def nearest_face_turn(yaw_difference):
    """A cube-minus-fingers yaw difference (rad) wrapped to [-pi/4, pi/4): the turn onto the nearest face (a cube
    is symmetric every 90 degrees). Floats, numpy arrays and torch tensors alike."""
    return (yaw_difference + np.pi / 4) % (np.pi / 2) - np.pi / 4


def cube_yaw_error(eef_quat_xyzw: np.ndarray, cube_quat_xyzw: np.ndarray) -> float:
    """The yaw (rad, in [-pi/4, pi/4)) that lines the fingers up with the nearest face of a cube."""
    return nearest_face_turn(yaw_of(cube_quat_xyzw) - yaw_of(eef_quat_xyzw))


def quat_slerp(q0_xyzw: np.ndarray, q1_xyzw: np.ndarray, fraction: float | np.ndarray) -> np.ndarray:
    """Spherical interpolation along the shorter arc."""
    q0 = quat_normalize(q0_xyzw)
    q1 = quat_normalize(q1_xyzw)
    fraction = np.asarray(fraction, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6
    w0 = np.where(near, 1.0 - fraction, np.sin((1.0 - fraction) * theta) / np.where(near, 1.0, sin_theta))
    w1 = np.where(near, fraction, np.sin(fraction * theta) / np.where(near, 1.0, sin_theta))
    return quat_normalize(w0 * q0 + w1 * q1)


def clamp_delta_pos(delta_pos_m: np.ndarray, max_norm_m: float = MAX_DELTA_POS_M) -> tuple[np.ndarray, bool]:
    """Scale a position delta down to `max_norm_m`; returns (clamped, whether it was clamped)."""
    delta_pos_m = np.asarray(delta_pos_m, dtype=np.float64)
    norm = float(np.linalg.norm(delta_pos_m))
    if norm > max_norm_m:
        return delta_pos_m * (max_norm_m / norm), True
    return delta_pos_m, False


def clamp_delta_quat(delta_quat_xyzw: np.ndarray, max_angle_rad: float = MAX_DELTA_ROT_RAD) -> tuple[np.ndarray, bool]:
    """Shorten a rotation delta to `max_angle_rad` about the same axis; canonical cover (w >= 0)."""
    rotvec = quat_to_rotvec(delta_quat_xyzw)
    angle = float(np.linalg.norm(rotvec))
    if angle > max_angle_rad:
        return quat_canonical(rotvec_to_quat(rotvec * (max_angle_rad / angle))), True
    return quat_canonical(quat_normalize(delta_quat_xyzw)), False


def gripper_class(gripper_command: float) -> float:
    """-1 (open) or +1 (closed) from any signed gripper command."""
    return GRIPPER_CLOSED if gripper_command > 0 else GRIPPER_OPEN


def make_delta_action(
    delta_pos_m: np.ndarray, delta_quat_xyzw: np.ndarray, gripper_command: float
) -> tuple[np.ndarray, bool]:
    """The 8-D action `[dx, dy, dz, qx, qy, qz, qw, gripper]`, clamped; returns (action, was_clamped)."""
    delta_pos_m, pos_clamped = clamp_delta_pos(delta_pos_m)
    delta_quat_xyzw, rot_clamped = clamp_delta_quat(delta_quat_xyzw)
    action = np.concatenate([delta_pos_m, delta_quat_xyzw, [gripper_class(gripper_command)]])
    return action, pos_clamped or rot_clamped


def delta_action_from_poses(
    pos_now_m: np.ndarray,
    quat_now_xyzw: np.ndarray,
    pos_next_m: np.ndarray,
    quat_next_xyzw: np.ndarray,
    gripper_command: float,
) -> tuple[np.ndarray, bool]:
    """Proprioception-derived action between two measured poses (base frame): `q_next * q_now^-1`."""
    delta_pos_m = np.asarray(pos_next_m, dtype=np.float64) - np.asarray(pos_now_m, dtype=np.float64)
    delta_quat_xyzw = quat_multiply(quat_normalize(quat_next_xyzw), quat_conjugate(quat_normalize(quat_now_xyzw)))
    return make_delta_action(delta_pos_m, delta_quat_xyzw, gripper_command)


def apply_delta_action(pos_m: np.ndarray, quat_xyzw: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose reached by applying an 8-D action to (pos, quat): the inverse of `delta_action_from_poses`."""
    action = np.asarray(action, dtype=np.float64)
    next_pos_m = np.asarray(pos_m, dtype=np.float64) + action[:3]
    next_quat_xyzw = quat_normalize(quat_multiply(quat_normalize(action[3:7]), quat_normalize(quat_xyzw)))
    return next_pos_m, next_quat_xyzw


def quat_rotate(quat_xyzw: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Rotate 3-vectors by unit quaternions (batched over leading dimensions)."""
    quat_xyzw = quat_normalize(quat_xyzw)
    vec = np.asarray(vec, dtype=np.float64)
    xyz, w = quat_xyzw[..., :3], quat_xyzw[..., 3:4]
    # v' = v + 2 w (u x v) + 2 u x (u x v), without building the matrix
    uv = np.cross(xyz, vec)
    return vec + 2.0 * w * uv + 2.0 * np.cross(xyz, uv)


def pose_compose(
    pos_a_m: np.ndarray, quat_a_xyzw: np.ndarray, pos_b_m: np.ndarray, quat_b_xyzw: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """T_a * T_b: pose b (given in frame a) expressed in a's parent frame."""
    pos_m = np.asarray(pos_a_m, dtype=np.float64) + quat_rotate(quat_a_xyzw, pos_b_m)
    return pos_m, quat_normalize(quat_multiply(quat_a_xyzw, quat_b_xyzw))


def pose_inverse(pos_m: np.ndarray, quat_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T^-1 of a rigid transform given as (position, quaternion)."""
    quat_inv_xyzw = quat_conjugate(quat_normalize(quat_xyzw))
    return -quat_rotate(quat_inv_xyzw, pos_m), quat_inv_xyzw


def quat_continuous(quat_xyzw: np.ndarray) -> np.ndarray:
    """A (T, 4) sequence with each quaternion on the cover nearest its predecessor (no sign jumps)."""
    quats = quat_normalize(quat_xyzw).copy()
    for t in range(1, len(quats)):
        if np.dot(quats[t], quats[t - 1]) < 0:
            quats[t] = -quats[t]
    return quats
