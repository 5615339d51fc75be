"""Timestamped streams read from one recorded episode, before alignment, and the converter's error type.

Every reader (ROS 1 bag, ROS 2 bag, HDF5) produces an `EpisodeStreams`; everything after is source-agnostic.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dataset_tools.writer import BadEpisodeError


class ConversionError(BadEpisodeError):
    """Bad input; the message names the file, the topic and the time."""


@dataclass
class JointStream:
    topic: str
    time_s: np.ndarray  # (N,) seconds since the episode's first message
    joint_pos_rad: np.ndarray  # (N, n_joints) in the topic map's joint order


@dataclass
class PoseStream:
    topic: str
    time_s: np.ndarray  # (N,)
    pos_base_m: np.ndarray  # (N, 3)
    quat_base_xyzw: np.ndarray  # (N, 4)


@dataclass
class GripperStream:
    topic: str
    time_s: np.ndarray  # (N,)
    closed: np.ndarray  # (N,) bool
    qpos: np.ndarray  # (N, 2) finger positions (or the scalar signal twice when it is a std_msgs topic)


@dataclass
class CameraStream:
    topic: str
    time_s: np.ndarray  # (N,)
    decode: Callable[[int], np.ndarray]  # frame index -> uint8 HxWx3 RGB (decoded only when used)


@dataclass
class EpisodeStreams:
    source: str  # the file (and demo) it came from, for error messages
    joints: JointStream
    gripper: GripperStream
    pose: PoseStream | None = None
    cameras: dict[str, CameraStream] = field(default_factory=dict)
    start_time_ns: int = 0  # absolute time of time_s == 0


def finger_opening_closed(finger_pos: np.ndarray, closed_below: float) -> np.ndarray:
    """Gripper closed where the finger opening (sum of |joint|, metres) is below the threshold."""
    return np.abs(np.asarray(finger_pos, dtype=np.float64)).reshape(len(finger_pos), -1).sum(axis=1) < closed_below


def check_timestamps(source: str, topic: str, time_s: np.ndarray, start_time_ns: int = 0) -> None:
    """Strictly increasing and finite, else an error naming the first offending message."""
    if len(time_s) == 0:
        raise ConversionError(f"{source}: topic {topic} has no messages")
    bad = np.flatnonzero(~np.isfinite(time_s))
    if bad.size:
        raise ConversionError(f"{source}: topic {topic}: message {bad[0]} has a non-finite timestamp")
    back = np.flatnonzero(np.diff(time_s) <= 0)
    if back.size:
        k = back[0] + 1
        raise ConversionError(
            f"{source}: topic {topic}: non-monotonic timestamps: message {k} at "
            f"{_abs_time(time_s[k], start_time_ns)} is not after message {k - 1} at {_abs_time(time_s[k - 1], start_time_ns)}"
        )


def check_finite(source: str, topic: str, time_s: np.ndarray, values: np.ndarray, what: str, start_time_ns: int = 0):
    bad = ~np.isfinite(np.asarray(values, dtype=np.float64).reshape(len(values), -1)).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise ConversionError(f"{source}: topic {topic} at {_abs_time(time_s[k], start_time_ns)}: non-finite {what}")


def check_quaternions(source: str, stream: PoseStream, start_time_ns: int = 0) -> None:
    norm = np.linalg.norm(stream.quat_base_xyzw, axis=1)
    bad = ~np.isfinite(norm) | (norm < 1e-6)
    if bad.any():
        k = int(np.argmax(bad))
        raise ConversionError(
            f"{source}: topic {stream.topic} at {_abs_time(stream.time_s[k], start_time_ns)}: "
            f"quaternion {stream.quat_base_xyzw[k].tolist()} has zero or non-finite norm"
        )


def check_streams(streams: EpisodeStreams) -> None:
    src, t0 = streams.source, streams.start_time_ns
    for stream in [streams.joints, streams.gripper, streams.pose, *streams.cameras.values()]:
        if stream is not None:
            check_timestamps(src, stream.topic, stream.time_s, t0)
    check_finite(src, streams.joints.topic, streams.joints.time_s, streams.joints.joint_pos_rad, "joint position", t0)
    if streams.pose is not None:
        check_finite(src, streams.pose.topic, streams.pose.time_s, streams.pose.pos_base_m, "position", t0)
        check_quaternions(src, streams.pose, t0)


def _abs_time(time_s: float, start_time_ns: int) -> str:
    if start_time_ns:
        return f"t={start_time_ns / 1e9 + time_s:.6f} s (+{time_s:.3f} s into the episode)"
    return f"t={time_s:.6f} s"
