"""From aligned streams to the dataset's frames: poses (pose topic or URDF forward kinematics),
proprio-derived 8-D actions with the clamps of method.md, observation.state, images, and trimming.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dataset_tools.convert.align import AlignedEpisode
from dataset_tools.convert.streams import ConversionError, EpisodeStreams, PoseStream
from lerobot_bcrl import features as F
from lerobot_bcrl.geometry import GRIPPER_CLOSED, GRIPPER_OPEN, delta_action_from_poses

TRIM_RULES = ("none", "until_grasp")


@dataclass
class EpisodeStats:
    n_frames: int
    n_clamped_actions: int
    n_trimmed_frames: int
    grasp_time_s: float  # first closed frame's time on the grid, -1 if never closed (NaN reads as missing)
    duration_s: float


def pose_from_joints(streams: EpisodeStreams, kinematics) -> PoseStream:
    """Tool poses by forward kinematics at every joint-state sample (then aligned like a pose topic)."""
    pos, quat = kinematics.forward(streams.joints.joint_pos_rad)
    return PoseStream(f"FK({streams.joints.topic})", streams.joints.time_s, pos, quat)


def square_resize(image: np.ndarray, size: int) -> np.ndarray:
    """Centre-crop to a square, then resize (area filter) to size x size."""
    import cv2

    height, width = image.shape[:2]
    side = min(height, width)
    top, left = (height - side) // 2, (width - side) // 2
    image = image[top : top + side, left : left + side]
    if side != size:
        image = cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(image, dtype=np.uint8)


def trim_end(aligned: AlignedEpisode, rule: str, after_grasp_s: float) -> int:
    """Number of grid frames to keep under the task-relevance rule."""
    if rule == "none":
        return len(aligned.time_s)
    if rule == "until_grasp":
        closed = np.flatnonzero(aligned.gripper_closed)
        if closed.size == 0:
            return len(aligned.time_s)
        keep = closed[0] + 1 + int(round(after_grasp_s * aligned.report.fps))
        return min(len(aligned.time_s), max(keep, 2))
    raise ValueError(f"trim must be one of {TRIM_RULES}, got {rule!r}")


def episode_frames(
    aligned: AlignedEpisode,
    streams: EpisodeStreams,
    image_size: int | None,
    camera_keys: dict[str, str],
    trim: str = "none",
    trim_after_grasp_s: float = 0.5,
) -> tuple[dict[str, np.ndarray], EpisodeStats]:
    """Frame t holds the observation at grid time t and the action that moves the pose to t + 1."""
    n_keep = trim_end(aligned, trim, trim_after_grasp_s)
    n = n_keep - 1  # the last kept pose has no successor: it only closes the previous action
    if n < 2:
        raise ConversionError(f"{aligned.source}: {n} frame(s) after alignment and trimming; at least 2 are needed")
    pos, quat = aligned.eef_pos_base_m[:n_keep], aligned.eef_quat_base_xyzw[:n_keep]
    gripper = np.where(aligned.gripper_closed[:n_keep], GRIPPER_CLOSED, GRIPPER_OPEN)
    actions, n_clamped = [], 0
    for t in range(n):
        # The gripper class is the state the step leads to: "close" on the step where the fingers close.
        action, clamped = delta_action_from_poses(pos[t], quat[t], pos[t + 1], quat[t + 1], gripper[t + 1])
        actions.append(action)
        n_clamped += int(clamped)
    action = np.stack(actions)
    state = np.concatenate([pos[:n], quat[:n], aligned.gripper_qpos[:n], aligned.joint_pos_rad[:n]], axis=1)
    frames: dict[str, np.ndarray] = {
        F.STATE_KEY: state,
        # Privileged object state does not exist on a real robot: zeros keep the features identical.
        F.ENV_STATE_KEY: np.zeros((n, F.ENV_STATE_DIM)),
        F.ACTION_KEY: action,
        F.AUX_EEF_POS_KEY: pos[:n],
        F.AUX_PROPRIO_ACTION_KEY: action,
        F.REWARD_KEY: np.zeros((n, 1)),
        F.DONE_KEY: (np.arange(n) == n - 1).reshape(n, 1),
        F.SUCCESS_KEY: np.zeros((n, 1), dtype=bool),
    }
    if image_size is not None:
        for name, key in camera_keys.items():
            decode = streams.cameras[name].decode
            index = aligned.camera_frame_index[name][:n]
            decoded: dict[int, np.ndarray] = {}  # a repeated frame is decoded once
            for i in np.unique(index).tolist():
                decoded[i] = square_resize(decode(i), image_size)
            frames[key] = np.stack([decoded[i] for i in index.tolist()])
    closed = np.flatnonzero(gripper[1 : n + 1] > 0)
    stats = EpisodeStats(
        n_frames=n,
        n_clamped_actions=n_clamped,
        n_trimmed_frames=len(aligned.time_s) - n_keep,
        grasp_time_s=float(aligned.time_s[closed[0] + 1]) if closed.size else -1.0,
        duration_s=float(aligned.time_s[n] - aligned.time_s[0]),
    )
    return frames, stats
