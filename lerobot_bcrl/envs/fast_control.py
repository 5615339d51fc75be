"""robosuite's control step for the Sawyer in Lift, without robosuite's per-substep Python.

robosuite runs its whole controller stack at each of the 25 physics substeps of a control step: the composite
controller, the OSC_POSE arm controller's reference update (four Jacobian evaluations, name look-ups, copies),
the gripper controller, the robot's bookkeeping and every observable's timer (80 % of a step's time,
docs/RESULTS.md#env-throughput). `FastControlStep` computes the same values:

- once per control step, the goal: robosuite's own `set_goal` of the arm and gripper controllers (the delta's
  scaling, the "achieved" goal in the base frame, the gripper's speed-limited command), so what an action means
  is robosuite's by construction;
- at each substep, the arm controller's `update()` and `run_controller()` (position and orientation error,
  velocity damping, the decoupled operational-space wrench, gravity compensation, the nullspace posture torque,
  the clip to the actuators' range) in two numba functions on MuJoCo's arrays: one `mj_jacSite` and one `mj_fullM`
  call, the same expressions in the same order, robosuite's own numba `opspace_matrices` and `orientation_error`
  on arrays of the same memory layout as robosuite's (the layout selects the compiled code, and so the last bits);
  the gripper's actuator command is constant over the control step.

The substep loop is MuJoCo's `mj_step1` / control / `mj_step2`, as robosuite's with `lite_physics`. The result is
robosuite's trajectory bit for bit on this machine (tests/test_fast_control.py compares whole episodes).
Controller settings other than the ones the Lift env uses (robosuite's default Sawyer OSC_POSE: fixed impedance,
delta input in the base frame, no interpolator, no limits, a fixed base) are refused rather than approximated.
"""

from __future__ import annotations

import mujoco
import numba
import numpy as np
from robosuite.controllers.parts.arm.osc import OperationalSpaceController
from robosuite.controllers.parts.gripper.simple_grip import SimpleGripController
from robosuite.utils.control_utils import opspace_matrices, orientation_error

ARM = "right"
GRIPPER = "right_gripper"


def _check_supported(sim_env) -> None:
    """Raise if robosuite's controllers are configured in a way `FastControlStep` does not compute."""
    robot = sim_env.robots[0]
    arm, gripper = robot.part_controllers.get(ARM), robot.part_controllers.get(GRIPPER)
    problems = []
    if len(sim_env.robots) != 1 or set(robot.part_controllers) != {ARM, GRIPPER}:
        problems.append(f"one arm and one gripper controller, got {sorted(robot.part_controllers)}")
    if not isinstance(arm, OperationalSpaceController) or not isinstance(gripper, SimpleGripController):
        problems.append(f"OSC arm and simple gripper controllers, got {type(arm).__name__}, {type(gripper).__name__}")
    else:
        expected = {
            "use_ori": True, "input_type": "delta", "input_ref_frame": "base", "impedance_mode": "fixed",
            "_goal_update_mode": "achieved", "uncoupling": True, "lite_physics": True,
            "interpolator_pos": None, "interpolator_ori": None, "position_limits": None, "orientation_limits": None,
        }  # fmt: skip
        problems += [f"{k}={getattr(arm, k)!r}" for k, v in expected.items() if getattr(arm, k) != v]
        if gripper.interpolator is not None or not gripper.use_action_scaling:
            problems.append("gripper controller with an interpolator or without action scaling")
    if arm is not None:
        model = sim_env.sim.model._model
        body = model.site_bodyid[model.site(f"{arm.naming_prefix}{arm.part_name}_center").id]
        while body != 0:  # the base site's velocity is taken as zero: no joint between it and the world
            if model.body_jntnum[body]:
                problems.append("a robot base that moves")
                break
            body = model.body_parentid[body]
    if not sim_env.lite_physics:
        problems.append("env.lite_physics=False")
    if problems:
        raise ValueError(f"fast control step does not support this robosuite configuration: {'; '.join(problems)}")


class FastControlStep:
    """One control step of a robosuite Lift env, as robosuite's `env.step` computes its physics.

    Use `reset()` after every robosuite reset, then `step(controller_action)` in place of `env.step` (robosuite's
    observables and the robot's history buffers are not updated; read observations from `sim.data`).
    """

    def __init__(self, sim_env):
        _check_supported(sim_env)
        self._env = sim_env
        self._model = sim_env.sim.model._model
        self._data = sim_env.sim.data._data
        self.n_substeps = int(sim_env.control_timestep / sim_env.model_timestep)  # robosuite's own expression
        robot = sim_env.robots[0]
        arm = robot.part_controllers[ARM]
        self._eef_site = self._model.site(arm.ref_name).id
        self._base_site = self._model.site(f"{arm.naming_prefix}{arm.part_name}_center").id
        self._arm_qpos = np.array(arm.qpos_index, dtype=np.int64)
        self._arm_dofs = np.array(arm.qvel_index, dtype=np.int64)
        actuators = robot._ref_actuators_indexes_dict
        self._arm_actuators = np.array(actuators[ARM], dtype=np.int64)
        self._gripper_actuators = np.array(actuators[GRIPPER], dtype=np.int64)
        ctrlrange = self._model.actuator_ctrlrange
        self._arm_ctrl_low, self._arm_ctrl_high = ctrlrange[self._arm_actuators, 0], ctrlrange[self._arm_actuators, 1]
        self._gripper_ctrl_low = ctrlrange[self._gripper_actuators, 0]
        self._gripper_ctrl_high = ctrlrange[self._gripper_actuators, 1]
        nv = self._model.nv
        self._jacp, self._jacr = np.zeros((3, nv)), np.zeros((3, nv))
        self._full_mass_matrix = np.zeros((nv, nv))
        n_arm = len(self._arm_dofs)
        self._reference = (
            np.zeros(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3),  # ref_pos, ref_ori_mat, ref_pos_vel, ref_ori_vel
            np.zeros((3, n_arm)), np.zeros((3, n_arm)), np.zeros((6, n_arm)),  # J_pos, J_ori, J_full
            np.zeros((n_arm, n_arm), order="F"), np.zeros(n_arm), np.zeros(n_arm),  # mass_matrix, joint_pos, joint_vel
        )  # fmt: skip  (robosuite's layouts: its Jacobians C-ordered, its indexed mass matrix Fortran-ordered)
        self._gripper_command: np.ndarray | None = None

    @property
    def _robot(self):
        return self._env.robots[0]

    def reset(self) -> None:
        """Read the state robosuite's reset gave the controllers (they are rebuilt at every reset)."""
        arm = self._robot.part_controllers[ARM]
        self._arm = arm
        self._gripper = self._robot.part_controllers[GRIPPER]
        self._gains = np.stack([arm.kp, arm.kd]).astype(np.float64)
        # The gripper controller's command = bias + weight * goal, from its actuators' range (fixed per controller).
        gripper_low, gripper_high = np.asarray(self._gripper.actuator_min), np.asarray(self._gripper.actuator_max)
        self._gripper_bias, self._gripper_weight = 0.5 * (gripper_high + gripper_low), 0.5 * (gripper_high - gripper_low)
        self._gripper_command = None

    def _set_goal(self, controller_action: np.ndarray) -> None:
        """robosuite's goal for this control step (composite controller `update_state` + `set_goal`)."""
        robot, arm, gripper = self._robot, self._arm, self._gripper
        robot.composite_controller.update_state()
        arm.set_goal(controller_action[:6])
        gripper.new_update = False  # its update() reads joint data its goal does not use
        gripper.set_goal(robot.gripper[ARM].format_action(controller_action[6:7]))
        arm.new_update = gripper.new_update = True  # as their run_controller leaves them: refresh at the next goal
        self._goal_pos = arm.goal_pos
        self._goal_ori = arm.goal_ori
        command = self._gripper_bias + self._gripper_weight * np.array(gripper.goal_qvel)
        self._gripper_command = np.clip(command, self._gripper_ctrl_low, self._gripper_ctrl_high)

    def _load_arm_reference(self) -> None:
        """Write this substep's reference data into the arm controller, as its update() would, and mark it fresh."""
        arm = self._arm
        ref_pos, ref_ori_mat, ref_pos_vel, ref_ori_vel, J_pos, J_ori, J_full, mass_matrix, joint_pos, joint_vel = self._reference
        arm.ref_pos[:] = ref_pos
        arm.ref_ori_mat[:, :] = ref_ori_mat
        arm.ref_pos_vel[:] = ref_pos_vel
        arm.ref_ori_vel[:] = ref_ori_vel
        arm.J_pos[:, :] = J_pos
        arm.J_ori[:, :] = J_ori
        arm.J_full[:, :] = J_full
        arm.mass_matrix = mass_matrix.copy(order="F")
        arm.joint_pos, arm.joint_vel = joint_pos.copy(), joint_vel.copy()
        arm.new_update = False

    def step(self, controller_action: np.ndarray) -> None:
        """robosuite's `env.step` physics for one 7-D controller action; advances the env's step counter and clock."""
        env, model, data, arm = self._env, self._model, self._data, self._arm
        env.timestep += 1
        for substep in range(self.n_substeps):
            mujoco.mj_step1(model, data)
            mujoco.mj_jacSite(model, data, self._jacp, self._jacr, self._eef_site)
            mujoco.mj_fullM(model, self._full_mass_matrix, data.qM)
            eef_and_jacobians = (data.site_xpos[self._eef_site], data.site_xmat[self._eef_site], self._jacp, self._jacr)
            joints = (data.qvel, data.qpos, self._full_mass_matrix, self._arm_qpos, self._arm_dofs)
            base = (data.site_xpos[self._base_site], data.site_xmat[self._base_site])
            if substep > 0:  # the common case in one call: reference data, torques, actuator commands
                _control_substep(
                    *eef_and_jacobians, *joints, *self._reference, self._goal_pos, self._goal_ori, *base,
                    arm.initial_joint, data.qfrc_bias, self._gains, self._arm_ctrl_low, self._arm_ctrl_high,
                    data.ctrl, self._arm_actuators, self._gripper_actuators, self._gripper_command,
                )
                mujoco.mj_step2(model, data)
                continue
            if arm.new_update:
                _arm_reference(*eef_and_jacobians, *joints, *self._reference)
                self._load_arm_reference()  # what the arm controller's update() in set_goal would compute
            else:
                # Right after a reset robosuite's set_goal and first substep read the data of the controller's
                # construction (before the gripper's joints were placed): use the arm controller's.
                robosuite_reference = (arm.ref_pos, arm.ref_ori_mat, arm.ref_pos_vel, arm.ref_ori_vel, arm.J_pos,
                                       arm.J_ori, arm.J_full, arm.mass_matrix, arm.joint_pos, arm.joint_vel)  # fmt: skip
                for ours, robosuites in zip(self._reference, robosuite_reference):
                    ours[...] = robosuites
            self._set_goal(controller_action)
            data.ctrl[self._arm_actuators] = _arm_torques(
                self._goal_pos, self._goal_ori, *base, *self._reference, arm.initial_joint, data.qfrc_bias,
                self._arm_dofs, self._gains, self._arm_ctrl_low, self._arm_ctrl_high,
            )
            data.ctrl[self._gripper_actuators] = self._gripper_command
            mujoco.mj_step2(model, data)
        env.cur_time += env.control_timestep


@numba.njit(cache=True)
def _arm_reference(eef_xpos, eef_xmat, jacp, jacr, qvel, qpos, full_mass_matrix, arm_qpos, arm_dofs,
                   ref_pos, ref_ori_mat, ref_pos_vel, ref_ori_vel, J_pos, J_ori, J_full, mass_matrix, joint_pos, joint_vel):  # fmt: skip
    """The arm controller's `update()` (Controller._update_single_reference and the mass matrix), in place."""
    ref_pos[:] = eef_xpos
    ref_ori_mat[:, :] = eef_xmat.reshape((3, 3))
    ref_pos_vel[:] = np.dot(jacp, qvel)
    ref_ori_vel[:] = np.dot(jacr, qvel)
    for j in range(arm_dofs.shape[0]):
        joint_pos[j] = qpos[arm_qpos[j]]
        joint_vel[j] = qvel[arm_dofs[j]]
        for i in range(3):
            J_pos[i, j] = J_full[i, j] = jacp[i, arm_dofs[j]]
            J_ori[i, j] = J_full[3 + i, j] = jacr[i, arm_dofs[j]]
        for i in range(arm_dofs.shape[0]):
            mass_matrix[i, j] = full_mass_matrix[arm_dofs[i], arm_dofs[j]]


@numba.njit(cache=True)
def _control_substep(eef_xpos, eef_xmat, jacp, jacr, qvel, qpos, full_mass_matrix, arm_qpos, arm_dofs,
                     ref_pos, ref_ori_mat, ref_pos_vel, ref_ori_vel, J_pos, J_ori, J_full, mass_matrix, joint_pos,
                     joint_vel, goal_pos, goal_ori, origin_xpos, origin_xmat, initial_joint, qfrc_bias, gains, ctrl_low,
                     ctrl_high, ctrl, arm_actuators, gripper_actuators, gripper_command):  # fmt: skip
    """One substep after the first: _arm_reference, _arm_torques and the actuator commands, in one call."""
    _arm_reference(eef_xpos, eef_xmat, jacp, jacr, qvel, qpos, full_mass_matrix, arm_qpos, arm_dofs, ref_pos,
                   ref_ori_mat, ref_pos_vel, ref_ori_vel, J_pos, J_ori, J_full, mass_matrix, joint_pos, joint_vel)  # fmt: skip
    torques = _arm_torques(goal_pos, goal_ori, origin_xpos, origin_xmat, ref_pos, ref_ori_mat, ref_pos_vel,
                           ref_ori_vel, J_pos, J_ori, J_full, mass_matrix, joint_pos, joint_vel, initial_joint,
                           qfrc_bias, arm_dofs, gains, ctrl_low, ctrl_high)  # fmt: skip
    for i in range(arm_actuators.shape[0]):
        ctrl[arm_actuators[i]] = torques[i]
    for i in range(gripper_actuators.shape[0]):
        ctrl[gripper_actuators[i]] = gripper_command[i]


@numba.njit(cache=True)
def _arm_torques(goal_pos, goal_ori, origin_xpos, origin_xmat, ref_pos, ref_ori_mat, ref_pos_vel, ref_ori_vel,
                 J_pos, J_ori, J_full, mass_matrix, joint_pos, joint_vel, initial_joint, qfrc_bias, arm_dofs, gains,
                 ctrl_low, ctrl_high):  # fmt: skip
    """OperationalSpaceController.run_controller (fixed impedance, decoupled, fixed base) and robosuite's clip to
    the actuators' control range. gains = (kp, kd) rows of 6."""
    origin_ori = origin_xmat.reshape((3, 3)).copy()
    desired_world_pos = origin_xpos + np.dot(origin_ori, goal_pos)
    desired_world_ori = np.dot(origin_ori, goal_ori)
    ori_error = orientation_error(desired_world_ori, ref_ori_mat)
    position_error = desired_world_pos - ref_pos
    # The base is welded to the world (checked at construction): its site velocity is zero.
    desired_force = position_error * gains[0, 0:3] + (-ref_pos_vel) * gains[1, 0:3]
    desired_torque = ori_error * gains[0, 3:6] + (-ref_ori_vel) * gains[1, 3:6]
    _, lambda_pos, lambda_ori, nullspace_matrix = opspace_matrices(mass_matrix, J_full, J_pos, J_ori)
    decoupled_wrench = np.concatenate((np.dot(lambda_pos, desired_force), np.dot(lambda_ori, desired_torque)))
    torques = np.dot(J_full.T, decoupled_wrench) + qfrc_bias[arm_dofs]
    # control_utils.nullspace_torques with its default joint_kp=10
    joint_kv = np.sqrt(10) * 2
    pose_torques = np.dot(mass_matrix, (10 * (initial_joint - joint_pos) - joint_kv * joint_vel))
    torques += np.dot(nullspace_matrix.transpose(), pose_torques)
    return np.minimum(np.maximum(torques, ctrl_low), ctrl_high)
