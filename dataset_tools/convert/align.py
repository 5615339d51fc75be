"""Align streams recorded at different, jittery rates onto one grid at the dataset's fps.

Joints are interpolated linearly, poses by lerp + slerp, the gripper is held from its last sample, and
each camera contributes its nearest frame; what was interpolated, dropped or repeated is counted.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from dataset_tools.convert.streams import ConversionError, EpisodeStreams, PoseStream
from lerobot_bcrl.geometry import quat_continuous, quat_slerp


@dataclass
class AlignmentReport:
    fps: float
    n_frames: int = 0
    start_s: float = 0.0
    end_s: float = 0.0
    joint_samples: int = 0
    joint_max_gap_s: float = 0.0
    joint_gaps: int = 0  # holes longer than 2.5 median periods (dropped joint messages), interpolated across
    pose_source: str = ""
    camera_frames_received: dict[str, int] = field(default_factory=dict)
    camera_frames_dropped: dict[str, int] = field(default_factory=dict)  # received, used by no grid frame
    camera_frames_repeated: dict[str, int] = field(default_factory=dict)  # grid frames reusing the previous one
    camera_max_offset_s: dict[str, float] = field(default_factory=dict)  # |grid time - frame time|

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class AlignedEpisode:
    """Everything on one time grid (N frames at fps); images stay undecoded until asked for."""

    source: str
    time_s: np.ndarray  # (N,)
    joint_pos_rad: np.ndarray  # (N, 7)
    eef_pos_base_m: np.ndarray  # (N, 3)
    eef_quat_base_xyzw: np.ndarray  # (N, 4), sign-continuous
    gripper_closed: np.ndarray  # (N,) bool
    gripper_qpos: np.ndarray  # (N, 2)
    camera_frame_index: dict[str, np.ndarray]  # name -> (N,) index into the camera stream
    report: AlignmentReport


def interpolate_linear(time_s: np.ndarray, values: np.ndarray, grid_s: np.ndarray) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    return np.stack([np.interp(grid_s, time_s, column) for column in values.reshape(len(values), -1).T], axis=1)


def interpolate_poses(pose: PoseStream, grid_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions linearly, orientations by slerp between the two samples around each grid time."""
    pos = interpolate_linear(pose.time_s, pose.pos_base_m, grid_s)
    upper = np.clip(np.searchsorted(pose.time_s, grid_s, side="right"), 1, len(pose.time_s) - 1)
    lower = upper - 1
    span = pose.time_s[upper] - pose.time_s[lower]
    fraction = np.clip((grid_s - pose.time_s[lower]) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    quat = quat_slerp(pose.quat_base_xyzw[lower], pose.quat_base_xyzw[upper], fraction)
    return pos, quat_continuous(quat)


def hold_last(time_s: np.ndarray, grid_s: np.ndarray) -> np.ndarray:
    """Index of the latest sample at or before each grid time (the first one before it starts)."""
    return np.clip(np.searchsorted(time_s, grid_s, side="right") - 1, 0, len(time_s) - 1)


def nearest(time_s: np.ndarray, grid_s: np.ndarray) -> np.ndarray:
    upper = np.clip(np.searchsorted(time_s, grid_s), 0, len(time_s) - 1)
    lower = np.clip(upper - 1, 0, len(time_s) - 1)
    return np.where(np.abs(time_s[lower] - grid_s) <= np.abs(time_s[upper] - grid_s), lower, upper)


def align(streams: EpisodeStreams, pose: PoseStream, fps: float) -> AlignedEpisode:
    """Resample onto `start + k / fps` over the span that every stream covers."""
    report = AlignmentReport(fps=fps, pose_source=pose.topic)
    timed = [streams.joints.time_s, pose.time_s, *(c.time_s for c in streams.cameras.values())]
    start_s = max(t[0] for t in timed)
    end_s = min(t[-1] for t in timed)
    grid_s = start_s + np.arange(int(np.floor((end_s - start_s) * fps + 1e-9)) + 1) / fps if end_s >= start_s else np.array([])
    if len(grid_s) < 2:
        raise ConversionError(
            f"{streams.source}: the streams overlap for {max(end_s - start_s, 0.0):.3f} s "
            f"(from {start_s:.3f} s to {end_s:.3f} s): fewer than 2 frames at {fps} fps"
        )
    joint_t = streams.joints.time_s
    gaps = np.diff(joint_t)
    report.n_frames, report.start_s, report.end_s = len(grid_s), float(grid_s[0]), float(grid_s[-1])
    report.joint_samples = len(joint_t)
    report.joint_max_gap_s = float(gaps.max()) if len(gaps) else 0.0
    report.joint_gaps = int((gaps > 2.5 * np.median(gaps)).sum()) if len(gaps) else 0
    eef_pos, eef_quat = interpolate_poses(pose, grid_s)
    gripper_index = hold_last(streams.gripper.time_s, grid_s)
    frame_index = {}
    for name, camera in streams.cameras.items():
        index = nearest(camera.time_s, grid_s)
        frame_index[name] = index
        report.camera_frames_received[name] = len(camera.time_s)
        in_span = (camera.time_s >= grid_s[0] - 0.5 / fps) & (camera.time_s <= grid_s[-1] + 0.5 / fps)
        used = np.zeros(len(camera.time_s), dtype=bool)
        used[index] = True  # a grid end may use a frame just outside the span: count unused frames inside it
        report.camera_frames_dropped[name] = int((in_span & ~used).sum())
        report.camera_frames_repeated[name] = int((np.diff(index) == 0).sum())
        report.camera_max_offset_s[name] = float(np.abs(camera.time_s[index] - grid_s).max())
    return AlignedEpisode(
        source=streams.source,
        time_s=grid_s,
        joint_pos_rad=interpolate_linear(joint_t, streams.joints.joint_pos_rad, grid_s),
        eef_pos_base_m=eef_pos,
        eef_quat_base_xyzw=eef_quat,
        gripper_closed=streams.gripper.closed[gripper_index],
        gripper_qpos=np.asarray(streams.gripper.qpos, dtype=np.float64)[gripper_index],
        camera_frame_index=frame_index,
        report=report,
    )
