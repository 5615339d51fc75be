"""A simulated lab rig: robosuite's MuJoCo Sawyer and the Lift cube (the towel's corner) behind the same
`JointVelocityTransport` a real arm implements, with physics between the commands.

`PhysicsSawyerTransport` runs the arm the way a real one runs in joint-velocity mode: every 2 ms physics step
applies gravity and Coriolis compensation plus a velocity loop `M @ (gain * (commanded - measured velocity))`,
within the actuators' torque limits, and the gripper's position actuators go to open or closed. The arm lags its
commands, the torque limits cap it and contacts push it: what it does is not what was commanded, as on hardware.
`SimulatedLiftRig` adds what a lab has around the arm: a camera, object placement per start, and the checks
that score a run (reach, grasp, lift).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from lerobot_bcrl.envs.lift import LiftEnv, cube_yaw_features
from lerobot_bcrl.geometry import pose_compose, pose_inverse
from lerobot_bcrl.features import STATE_DIM, STATE_EEF_POS, STATE_EEF_QUAT
from lerobot_bcrl.robot.kinematics import SAWYER_ARM_JOINTS, UrdfKinematics
from lerobot_bcrl.robot.mujoco_sawyer import (
    GRIP_SITE_IN_RIGHT_HAND_POS_M,
    GRIP_SITE_IN_RIGHT_HAND_QUAT_XYZW,
    MujocoSawyer,
    wxyz_to_xyzw,
)

GRIPPER_ACTUATORS = ("gripper0_right_gripper_r_finger_joint", "gripper0_right_gripper_l_finger_joint")
BASE_COLLISION_GEOM = "robot0_base_col"
VELOCITY_LOOP_GAIN_PER_S = 50.0  # the arm's velocity error decays with a ~20 ms time constant
REACHED_WITHIN_M = 0.02  # grip site to cube centre: the fingers are around the cube (its half-size is 0.02 m)
LIFTED_ABOVE_START_M = 0.04  # the cube's rise that robosuite's Lift counts as success


class PhysicsSawyerTransport:
    """The MuJoCo Sawyer in joint-velocity mode; `on_physics_step()` is called after every physics step."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData):
        self.model, self.data = model, data
        self.sawyer = MujocoSawyer(model)
        self.on_physics_step: Callable[[], None] | None = None
        self._arm_actuators = np.array([model.actuator(f"robot0_torq_{n}").id for n in SAWYER_ARM_JOINTS])
        self._torque_limit = model.actuator_ctrlrange[self._arm_actuators, 1]
        fingers = [model.actuator(name).id for name in GRIPPER_ACTUATORS]
        # The right finger closes towards its range's top, the left towards its bottom (rethink_gripper.xml).
        r_range, l_range = model.actuator_ctrlrange[fingers[0]], model.actuator_ctrlrange[fingers[1]]
        self._finger_actuators = np.array(fingers)
        self._finger_ctrl = {True: np.array([r_range[1], l_range[0]]), False: np.array([r_range[0], l_range[1]])}
        self._mass_matrix = np.zeros((model.nv, model.nv))
        self.joint_vel_command_rad_s = np.zeros(len(self._arm_actuators))
        self.gripper_closed = False
        self._grid_start_s = 0.0  # the period grid: period k ends at round((k + 1) * period / dt) physics steps
        self._grid_period_s: float | None = None
        self._periods_done = 0

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    def read_joint_positions(self) -> np.ndarray:
        return self.sawyer.joint_pos_rad(self.data)

    def send(self, joint_vel_rad_s: np.ndarray, gripper_closed: bool) -> None:
        self.joint_vel_command_rad_s = np.asarray(joint_vel_rad_s, dtype=np.float64).copy()
        self.gripper_closed = bool(gripper_closed)

    def wait_period(self, period_s: float) -> None:
        """Step the physics to the end of this period. Periods end on a grid of `period_s` like a rig's timer (1/30 s
        is 16.7 physics steps: 17, 17, 16, ...), so the mean rate is the asked one; the grid restarts when the period
        changes or the time is not where the last period ended (a reset)."""
        dt = self.model.opt.timestep
        grid_now_s = self._grid_start_s + self._steps_to_period_end(self._periods_done, period_s) * dt
        if period_s != self._grid_period_s or abs(self.data.time - grid_now_s) > dt / 2:
            self._grid_start_s, self._grid_period_s, self._periods_done = float(self.data.time), period_s, 0
        k = self._periods_done
        n_steps = max(1, self._steps_to_period_end(k + 1, period_s) - self._steps_to_period_end(k, period_s))
        self._periods_done += 1
        dofs = self.sawyer.arm_dof_adr
        for _ in range(n_steps):
            mujoco.mj_fullM(self.model, self._mass_matrix, self.data.qM)
            velocity_error = self.joint_vel_command_rad_s - self.data.qvel[dofs]
            torque = self._mass_matrix[np.ix_(dofs, dofs)] @ (VELOCITY_LOOP_GAIN_PER_S * velocity_error)
            torque += self.data.qfrc_bias[dofs]
            self.data.ctrl[self._arm_actuators] = np.clip(torque, -self._torque_limit, self._torque_limit)
            self.data.ctrl[self._finger_actuators] = self._finger_ctrl[self.gripper_closed]
            mujoco.mj_step(self.model, self.data)
            if self.on_physics_step is not None:
                self.on_physics_step()


    def _steps_to_period_end(self, n_periods: int, period_s: float) -> int:
        return int(round(n_periods * period_s / self.model.opt.timestep))


def sawyer_kinematics(urdf_path: str | Path) -> UrdfKinematics:
    """The URDF's kinematics to robosuite's grip site: the tool point every pose of the rig refers to."""
    return UrdfKinematics(
        urdf_path,
        tool_offset_pos_m=GRIP_SITE_IN_RIGHT_HAND_POS_M,
        tool_offset_quat_xyzw=GRIP_SITE_IN_RIGHT_HAND_QUAT_XYZW,
    )


class SimulatedLiftRig:
    """The Lift scene as a lab bench: `reset(seed)` places the cube, `transport` moves the arm, `state()` reads the
    proprioception a rig records (tool pose in the base frame, finger joints, arm joints: `observation.state`)."""

    def __init__(self, image_size: int | None = None):
        from lerobot_bcrl.envs.rendering import CameraRenderer
        from lerobot_bcrl.features import CAMERA_NAME

        self.env = LiftEnv(obs_type="agent_pos", sim_step="robosuite")  # its model is kept across resets
        sim = self.env.sim_env.sim
        self.model, self.data = sim.model._model, sim.data._data
        # robosuite's Sawyer base is welded to the world, so MuJoCo does not filter its contact with the first link,
        # and that contact's friction locks joint 0 (robosuite's own controllers move the other six joints around
        # it). A real Sawyer turns its first joint: the fixed base's collision geom collides with nothing here.
        base_col = self.model.geom(BASE_COLLISION_GEOM).id
        self.model.geom_contype[base_col] = self.model.geom_conaffinity[base_col] = 0
        self.sawyer = MujocoSawyer(self.model)
        self.transport = PhysicsSawyerTransport(self.model, self.data)
        self.camera = CameraRenderer(self.model, CAMERA_NAME, image_size, image_size) if image_size else None
        self._cube_body = self.env.sim_env.cube_body_id
        self.cube_start_pos_base_m = np.zeros(3)
        self.closest_approach_m = np.inf
        self._last_tool_quat: np.ndarray | None = None

    def reset(self, seed: int) -> None:
        self.env.reset(seed=seed)
        self._last_tool_quat = None
        self.transport.send(np.zeros(7), gripper_closed=False)
        self.cube_start_pos_base_m = self.cube_pose_base()[0]
        self.closest_approach_m = np.inf
        self.update_scores()

    def state(self) -> np.ndarray:
        """`observation.state`: [tool pos (m), tool quat xyzw, 2 finger joints, 7 arm joints (rad)], base frame. The
        quaternion stays on the cover nearest the previous call's since the reset, as bcrl-convert writes episodes
        (a downward tool's quaternion changes sign as its yaw crosses 45 degrees)."""
        pos, quat = self.sawyer.grip_site_pose_base(self.data)
        if self._last_tool_quat is not None and np.dot(quat, self._last_tool_quat) < 0:
            quat = -quat
        self._last_tool_quat = quat
        state = np.concatenate([pos, quat, self.sawyer.finger_pos_m(self.data), self.sawyer.joint_pos_rad(self.data)])
        assert state.shape == (STATE_DIM,)
        return state

    def cube_pose_base(self) -> tuple[np.ndarray, np.ndarray]:
        base_inv_pos, base_inv_quat = pose_inverse(
            self.data.xpos[self.sawyer.base_body], wxyz_to_xyzw(self.data.xquat[self.sawyer.base_body])
        )
        return pose_compose(
            base_inv_pos, base_inv_quat, self.data.xpos[self._cube_body], wxyz_to_xyzw(self.data.xquat[self._cube_body])
        )

    def privileged_observation(self) -> dict[str, np.ndarray]:
        """What a scripted operator sees, in LiftEnv's layout and the base frame: the cube's pose too, which a
        human operator sees by eye and a policy on this rig does not get."""
        state = self.state()
        cube_pos, cube_quat = self.cube_pose_base()
        environment_state = np.concatenate(
            [cube_pos, cube_quat, cube_pos - state[STATE_EEF_POS], cube_yaw_features(state[STATE_EEF_QUAT], cube_quat)]
        )
        return {"agent_pos": state, "environment_state": environment_state}

    def render(self) -> np.ndarray:
        return self.camera.render(self.data)

    # -- scoring ----------------------------------------------------------------------------------------
    def update_scores(self) -> None:
        """Call once per control period: keeps the closest the tool came to the cube."""
        tool_pos = self.sawyer.grip_site_pose_base(self.data)[0]
        self.closest_approach_m = min(self.closest_approach_m, float(np.linalg.norm(self.cube_pose_base()[0] - tool_pos)))

    @property
    def reached(self) -> bool:
        return self.closest_approach_m < REACHED_WITHIN_M

    @property
    def grasped(self) -> bool:
        """The fingers hold the cube now (robosuite's contact check of both finger pads)."""
        sim_env = self.env.sim_env
        return bool(sim_env._check_grasp(gripper=sim_env.robots[0].gripper, object_geoms=sim_env.cube))

    @property
    def lifted(self) -> bool:
        return bool(self.cube_pose_base()[0][2] - self.cube_start_pos_base_m[2] > LIFTED_ABOVE_START_M)

    def close(self) -> None:
        if self.camera is not None:
            self.camera.close()
        self.env.close()
