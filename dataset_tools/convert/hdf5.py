"""Reader of robomimic/RoboTurk-style HDF5 (`data/demo_N/obs/...`) into `EpisodeStreams`, one per demo.

These files carry no timestamps: samples are taken as evenly spaced at the file's rate (`--hdf5.fps`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dataset_tools.convert.streams import (
    CameraStream,
    ConversionError,
    EpisodeStreams,
    GripperStream,
    JointStream,
    PoseStream,
    finger_opening_closed,
)


@dataclass
class Hdf5Keys:
    fps: float = 20.0  # the rate the file was recorded at (robosuite's default control rate)
    joint_pos: str = "obs/robot0_joint_pos"
    eef_pos: str = "obs/robot0_eef_pos"  # "" -> forward kinematics of joint_pos
    eef_quat: str = "obs/robot0_eef_quat"  # xyzw, robosuite's convention
    gripper_qpos: str = "obs/robot0_gripper_qpos"
    gripper_closed_below: float = 0.012  # opening (sum of |finger|) below this (m) -> closed (see TopicMap)
    camera_prefix: str = "obs/"  # camera <name> is read from <prefix><name>_image


def is_hdf5(path: Path) -> bool:
    return Path(path).suffix in (".hdf5", ".h5")


def demo_names(path: Path) -> list[str]:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if "data" not in f:
                raise ConversionError(f"{path}: no 'data' group (not a robomimic-style file)")
            return sorted(f["data"].keys(), key=lambda n: (len(n), n))
    except OSError as err:
        raise ConversionError(f"{path}: cannot open the HDF5 file, truncated or corrupt? ({err})") from err


def read_demo(path: Path, demo: str, keys: Hdf5Keys, camera_names: list[str]) -> EpisodeStreams:
    import h5py

    source = f"{path}:data/{demo}"
    with h5py.File(path, "r") as f:
        group = f["data"][demo]

        def dataset(key: str) -> np.ndarray:
            if key not in group:
                raise ConversionError(f"{source}: key {key!r} is missing (has {sorted(_keys(group))})")
            try:
                return np.asarray(group[key][()])
            except OSError as err:
                raise ConversionError(f"{source}: key {key!r} cannot be read ({err})") from err

        joint_pos = dataset(keys.joint_pos).astype(np.float64)
        time_s = np.arange(len(joint_pos)) / keys.fps
        finger = dataset(keys.gripper_qpos).astype(np.float64)
        pose = None
        if keys.eef_pos:
            pose = PoseStream(keys.eef_pos, time_s, dataset(keys.eef_pos).astype(np.float64), dataset(keys.eef_quat).astype(np.float64))
        cameras = {}
        for name in camera_names:
            frames = dataset(f"{keys.camera_prefix}{name}_image")
            if len(frames) == 0:
                raise ConversionError(f"{source}: camera '{name}' has no frames")
            cameras[name] = CameraStream(f"{keys.camera_prefix}{name}_image", time_s[: len(frames)], lambda i, fr=frames: fr[i])
    return EpisodeStreams(
        source=source,
        joints=JointStream(keys.joint_pos, time_s, joint_pos),
        gripper=GripperStream(keys.gripper_qpos, time_s[: len(finger)], finger_opening_closed(finger, keys.gripper_closed_below), finger),
        pose=pose,
        cameras=cameras,
    )


def _keys(group) -> list[str]:
    names = []
    group.visit(names.append)
    return names
