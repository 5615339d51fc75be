"""Forward and inverse kinematics of an arm described by a URDF, with pybullet (no ROS, no GUI).

The same object serves the converter (FK of recorded joint states) and the real-robot command path (IK).
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lerobot_bcrl.geometry import IDENTITY_QUAT_XYZW, pose_compose, pose_inverse, quat_normalize

SAWYER_ARM_JOINTS = tuple(f"right_j{i}" for i in range(7))
SAWYER_EEF_LINK = "right_hand"


class KinematicsError(ValueError):
    """A URDF that cannot serve the requested joints or link; the message names the file."""


def urdf_without_visuals(urdf_path: Path, out_dir: Path) -> Path:
    """A copy of the URDF without `<visual>` elements: their meshes (package://...) are rarely on disk,
    and pybullet refuses the whole file when one is missing. Kinematics need none of them."""
    text = Path(urdf_path).read_text()
    text = re.sub(r"<visual\b.*?</visual>", "", text, flags=re.DOTALL)
    text = re.sub(r"<visual\b[^>]*/>", "", text)
    # Collision meshes would fail the same way; kinematics only need the joints and inertias.
    text = re.sub(r"<collision\b.*?</collision>", "", text, flags=re.DOTALL)
    out = Path(out_dir) / Path(urdf_path).name
    out.write_text(text)
    return out


@contextlib.contextmanager
def _quiet_c_stdout():
    """Silence Bullet's C-level warnings (missing inertias of frame-only links) while loading."""
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


class UrdfKinematics:
    """FK/IK of `joint_names` to `eef_link` (plus a fixed tool offset), in the URDF's base frame.

    Joint positions are radians in the order of `joint_names`. One pybullet DIRECT client per instance.
    """

    def __init__(
        self,
        urdf_path: str | Path,
        joint_names: Sequence[str] = SAWYER_ARM_JOINTS,
        eef_link: str = SAWYER_EEF_LINK,
        tool_offset_pos_m: Sequence[float] = (0.0, 0.0, 0.0),
        tool_offset_quat_xyzw: Sequence[float] = tuple(IDENTITY_QUAT_XYZW),
    ):
        import pybullet

        self._p = pybullet
        self.urdf_path = Path(urdf_path)
        if not self.urdf_path.is_file():
            raise KinematicsError(f"{self.urdf_path}: URDF not found")
        self.joint_names = tuple(joint_names)
        self.eef_link = eef_link
        self.tool_offset_pos_m = np.asarray(tool_offset_pos_m, dtype=np.float64)
        self.tool_offset_quat_xyzw = quat_normalize(tool_offset_quat_xyzw)
        self._client = pybullet.connect(pybullet.DIRECT)
        with tempfile.TemporaryDirectory() as tmp:
            clean = urdf_without_visuals(self.urdf_path, Path(tmp))
            try:
                with _quiet_c_stdout():
                    self._body = pybullet.loadURDF(str(clean), useFixedBase=True, physicsClientId=self._client)
            except pybullet.error as err:
                pybullet.disconnect(self._client)
                raise KinematicsError(f"{self.urdf_path}: pybullet cannot load it ({err})") from err
        self._index_of_joint: dict[str, int] = {}
        self._index_of_link: dict[str, int] = {}
        movable = []  # pybullet's IK returns one value per non-fixed joint, in index order
        lower, upper, max_vel = {}, {}, {}
        for index in range(pybullet.getNumJoints(self._body, physicsClientId=self._client)):
            info = pybullet.getJointInfo(self._body, index, physicsClientId=self._client)
            name, joint_type = info[1].decode(), info[2]
            self._index_of_joint[name] = index
            self._index_of_link[info[12].decode()] = index
            if joint_type != pybullet.JOINT_FIXED:
                movable.append(name)
            lower[name], upper[name], max_vel[name] = info[8], info[9], info[11]
        missing = [n for n in self.joint_names if n not in self._index_of_joint]
        if missing:
            raise KinematicsError(
                f"{self.urdf_path}: joints {missing} are not in the URDF (it has {sorted(self._index_of_joint)})"
            )
        if eef_link not in self._index_of_link:
            raise KinematicsError(f"{self.urdf_path}: link {eef_link!r} is not in the URDF")
        self._joint_indices = [self._index_of_joint[n] for n in self.joint_names]
        self._eef_index = self._index_of_link[eef_link]
        self._movable_names = movable
        self._ik_columns = [movable.index(n) for n in self.joint_names]
        self.joint_lower_rad = np.array([lower[n] for n in self.joint_names])
        self.joint_upper_rad = np.array([upper[n] for n in self.joint_names])
        self.joint_max_vel_rad_s = np.array([max_vel[n] for n in self.joint_names])
        self._movable_lower = [lower[n] for n in movable]
        self._movable_upper = [upper[n] for n in movable]

    # -- forward ---------------------------------------------------------------------------------------
    def _set_joints(self, joint_pos_rad: np.ndarray) -> None:
        for index, value in zip(self._joint_indices, joint_pos_rad, strict=True):
            self._p.resetJointState(self._body, index, float(value), physicsClientId=self._client)

    def _link_pose(self) -> tuple[np.ndarray, np.ndarray]:
        state = self._p.getLinkState(
            self._body, self._eef_index, computeForwardKinematics=True, physicsClientId=self._client
        )
        return np.asarray(state[4], dtype=np.float64), np.asarray(state[5], dtype=np.float64)

    def forward(self, joint_pos_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool pose `(pos_base_m, quat_base_xyzw)`; batched over a leading (T,) axis when given (T, n)."""
        joint_pos_rad = np.asarray(joint_pos_rad, dtype=np.float64)
        if joint_pos_rad.ndim == 2:
            poses = [self.forward(q) for q in joint_pos_rad]
            return np.stack([p for p, _ in poses]), np.stack([q for _, q in poses])
        self._set_joints(joint_pos_rad)
        link_pos, link_quat = self._link_pose()
        return pose_compose(link_pos, link_quat, self.tool_offset_pos_m, self.tool_offset_quat_xyzw)

    # -- inverse ---------------------------------------------------------------------------------------
    def inverse(
        self,
        target_pos_base_m: np.ndarray,
        target_quat_base_xyzw: np.ndarray,
        seed_joint_pos_rad: np.ndarray,
        max_iterations: int = 200,
        residual_threshold_m: float = 1e-6,
        refinements: int = 3,
    ) -> np.ndarray:
        """Joint positions reaching the tool target, starting from `seed_joint_pos_rad`, within joint limits.

        pybullet's damped least squares restarts from the body's current joint state, so the seed is
        set first and the solve repeated `refinements` times from its own answer for accuracy.
        """
        inv_pos, inv_quat = pose_inverse(self.tool_offset_pos_m, self.tool_offset_quat_xyzw)
        link_pos, link_quat = pose_compose(target_pos_base_m, target_quat_base_xyzw, inv_pos, inv_quat)
        joint_pos = np.asarray(seed_joint_pos_rad, dtype=np.float64)
        ranges = [u - l for l, u in zip(self._movable_lower, self._movable_upper, strict=True)]
        for _ in range(refinements):
            self._set_joints(joint_pos)
            solution = self._p.calculateInverseKinematics(
                self._body,
                self._eef_index,
                link_pos.tolist(),
                link_quat.tolist(),
                lowerLimits=self._movable_lower,
                upperLimits=self._movable_upper,
                jointRanges=ranges,
                restPoses=self._rest_poses(joint_pos),
                maxNumIterations=max_iterations,
                residualThreshold=residual_threshold_m,
                physicsClientId=self._client,
            )
            joint_pos = np.clip(
                np.asarray(solution, dtype=np.float64)[self._ik_columns], self.joint_lower_rad, self.joint_upper_rad
            )
        return joint_pos

    def _rest_poses(self, joint_pos_rad: np.ndarray) -> list[float]:
        # pybullet's null-space term pulls toward the rest pose: the seed, so the arm does not wander.
        rest = [0.0] * len(self._movable_names)
        for column, value in zip(self._ik_columns, joint_pos_rad, strict=True):
            rest[column] = float(value)
        return rest

    def close(self) -> None:
        if self._client is not None and self._p.isConnected(self._client):
            self._p.disconnect(self._client)
        self._client = None

    def __enter__(self) -> UrdfKinematics:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
