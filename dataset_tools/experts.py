"""Experts that act in the Lift env: a scripted controller with privileged state, or any LeRobot policy.

Every expert returns actions in robosuite's normalised controller units (`[px, py, pz, rx, ry, rz,
gripper]` in [-1, 1]), because that is where the paper adds its noise (method.md section 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Protocol

import numpy as np

from lerobot_bcrl import geometry
from lerobot_bcrl.envs import controller
from lerobot_bcrl.features import STATE_EEF_POS, STATE_EEF_QUAT, STATE_GRIPPER_QPOS
from dataset_tools.noise import DemonstratorConfig


class Expert(Protocol):
    def reset(self) -> None: ...

    def act(self, observation: dict) -> np.ndarray:
        """Controller-unit action (7,) for one env observation (unbatched)."""
        ...


class Phase(IntEnum):
    APPROACH = 0
    DESCEND = 1
    CLOSE = 2
    LIFT = 3
    GIVE_UP = 4  # an operator who does not retry: hovers above the cube, open, to the end


# A planned miss closes the first grasp this much above the grasp point (uniform in the range) and up to
# MISS_MAX_ASIDE_M aside in a random direction: the fingers close on air above the cube, lift, find the
# cube left behind (the expert's "dropped it" rule) and retry.
MISS_HEIGHT_RANGE_M = (0.03, 0.045)
MISS_MAX_ASIDE_M = 0.015
# Sawyer's two finger joints read about +0.011 / -0.011 open; holding the Lift cube their difference stays
# above ~0.002, while fingers closed on nothing cross over to about -0.017.
EMPTY_GRASP_FINGER_GAP = -0.008


def sample_miss_offset(
    rng: np.random.Generator,
    height_range_m: tuple[float, float] = MISS_HEIGHT_RANGE_M,
    max_aside_m: float = MISS_MAX_ASIDE_M,
) -> np.ndarray:
    """Where a planned miss closes, relative to the grasp point (metres, world frame)."""
    angle = rng.uniform(0.0, 2 * np.pi)
    aside = max_aside_m * np.sqrt(rng.uniform())  # uniform over the disc
    return np.array([aside * np.cos(angle), aside * np.sin(angle), rng.uniform(*height_range_m)])


def fingers_closed_on_nothing(gripper_qpos: np.ndarray) -> bool:
    """Whether the two finger joints have closed past each other, i.e. with no object between them."""
    return float(gripper_qpos[0] - gripper_qpos[1]) < EMPTY_GRASP_FINGER_GAP


@dataclass
class ScriptedLiftExpert:
    """Approach above the cube, descend, close, lift, hold; retries if the cube slips out.

    `reset(miss_offset_m=...)` plans a miss: the first grasp closes that far from the grasp point, then the
    expert retries as after a drop. While it acts out the miss, `acting_on_planned_miss` is True.

    With `reopen_on_empty_grasp` the expert checks its fingers once closed: closed on nothing, it opens at
    once, wherever it is, and hovers above the cube again, instead of lifting with closed fingers until the
    cube is left 4 cm behind.

    `reset(skill=..., rng=...)` makes it act as an operator of that skill (`DemonstratorConfig`'s knobs: slower,
    hesitant, misaligned, closing too high, not always retrying), drawing from `rng`; the default skill is the
    plain expert, action for action.
    """

    hover_height_m: float = 0.06  # above the cube centre before descending
    grasp_depth_m: float = 0.0  # below the cube centre for the grip site
    max_descend_steps: int = 20  # close anyway once the fingers stall (on the table or the cube)
    lift_height_m: float = 0.15  # above the cube's start height
    close_steps: int = 8  # control steps spent closing the gripper
    position_gain: float = 2.0  # commanded delta per metre of error (OSC covers ~1/4 of a command per step)
    yaw_gain: float = 1.0  # fraction of the yaw error commanded per step
    reopen_on_empty_grasp: bool = False

    def reset(
        self,
        miss_offset_m: np.ndarray | None = None,
        skill: DemonstratorConfig | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.phase = Phase.APPROACH
        self._close_count = 0
        self._descend_count = 0
        self._cube_start_pos: np.ndarray | None = None
        self._miss_offset_m = None if miss_offset_m is None else np.asarray(miss_offset_m, dtype=np.float64)
        self._skill = skill if skill is not None else DemonstratorConfig()
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self._pause_steps_left = 0
        self._last_gripper = geometry.GRIPPER_OPEN
        self._new_attempt()

    def _new_attempt(self) -> None:
        """Draw this grasp attempt's mistakes: where the operator aims (offset, yaw) and whether it closes too high."""
        s = self._skill
        self._attempt_offset_m = np.zeros(3)
        self._attempt_yaw_rad = 0.0
        if s.grasp_offset_std_m > 0:
            self._attempt_offset_m[:2] = self._rng.normal(0.0, s.grasp_offset_std_m, size=2)
        if s.yaw_error_std_rad > 0:
            self._attempt_yaw_rad = float(self._rng.normal(0.0, s.yaw_error_std_rad))
        if s.close_too_high_probability > 0 and self._rng.uniform() < s.close_too_high_probability:
            self._attempt_offset_m[2] = self._rng.uniform(*MISS_HEIGHT_RANGE_M)

    @property
    def acting_on_planned_miss(self) -> bool:
        """Whether the last action was part of the planned miss (the miss ends when its closing is done)."""
        return self._miss_offset_m is not None

    def act(self, observation: dict) -> np.ndarray:
        state = np.asarray(observation["agent_pos"], dtype=np.float64)
        env_state = np.asarray(observation["environment_state"], dtype=np.float64)
        eef_pos, eef_quat = state[STATE_EEF_POS], state[STATE_EEF_QUAT]
        cube_pos, cube_quat = env_state[0:3], env_state[3:7]
        if self._cube_start_pos is None:
            self._cube_start_pos = cube_pos.copy()

        skill = self._skill
        if self._pause_steps_left == 0 and skill.hesitation_probability > 0:
            if self._rng.uniform() < skill.hesitation_probability:
                self._pause_steps_left = skill.hesitation_steps
        if self._pause_steps_left > 0:  # hesitating: no motion, the gripper kept as it was
            self._pause_steps_left -= 1
            return self._controller_action(np.zeros(3), geometry.IDENTITY_QUAT_XYZW, self._last_gripper)

        miss_offset = self._attempt_offset_m.copy()
        if self._miss_offset_m is not None:
            miss_offset += self._miss_offset_m
        hover = cube_pos + [miss_offset[0], miss_offset[1], self.hover_height_m]
        gripper = geometry.GRIPPER_OPEN
        if self.phase == Phase.APPROACH:
            target = hover
            if np.linalg.norm((target - eef_pos)[:2]) < 0.008 and abs(target[2] - eef_pos[2]) < 0.02:
                self.phase = Phase.DESCEND
        if self.phase == Phase.DESCEND:
            target = cube_pos - [0.0, 0.0, self.grasp_depth_m] + miss_offset
            self._descend_count += 1
            if np.linalg.norm((target - eef_pos)[:2]) > 0.02:  # pushed the cube: hover again
                self.phase = Phase.APPROACH
                self._descend_count = 0
                target = hover
            elif abs(target[2] - eef_pos[2]) < 0.01 or self._descend_count >= self.max_descend_steps:
                self.phase = Phase.CLOSE
        if self.phase == Phase.CLOSE:
            target = eef_pos
            gripper = geometry.GRIPPER_CLOSED
            self._close_count += 1
            if self._close_count >= self.close_steps:
                self.phase = Phase.LIFT
                self._miss_offset_m = None  # the planned miss is done; from here on, the plain expert
        if self.phase == Phase.LIFT:
            target = self._cube_start_pos + [0.0, 0.0, self.lift_height_m]
            gripper = geometry.GRIPPER_CLOSED
            # Closed on nothing (with the check), or the cube left behind: open, hover above it again.
            empty_grasp = self.reopen_on_empty_grasp and fingers_closed_on_nothing(state[STATE_GRIPPER_QPOS])
            if empty_grasp or np.linalg.norm(cube_pos - eef_pos) > 0.04:
                retry = skill.retry_probability >= 1.0 or self._rng.uniform() < skill.retry_probability
                self.phase = Phase.APPROACH if retry else Phase.GIVE_UP
                self._close_count = self._descend_count = 0
                gripper = geometry.GRIPPER_OPEN
                if retry:
                    self._new_attempt()
        if self.phase == Phase.GIVE_UP:
            target = cube_pos + [0.0, 0.0, self.hover_height_m]

        delta_pos_m = self.position_gain * (target - eef_pos)
        if skill.speed != 1.0:  # slower on the whole way, not only near the target: scale the clamped step
            delta_pos_m = skill.speed * geometry.clamp_delta_pos(delta_pos_m)[0]
        delta_quat = self._yaw_alignment(eef_quat, cube_quat) if self.phase <= Phase.DESCEND else None
        if delta_quat is None:
            delta_quat = geometry.IDENTITY_QUAT_XYZW
        self._last_gripper = gripper
        return self._controller_action(delta_pos_m, delta_quat, gripper)

    @staticmethod
    def _controller_action(delta_pos_m: np.ndarray, delta_quat_xyzw: np.ndarray, gripper: float) -> np.ndarray:
        action, _ = geometry.make_delta_action(delta_pos_m, delta_quat_xyzw, gripper)
        controller_action, _ = controller.delta_action_to_controller(action)
        return controller_action

    def _yaw_alignment(self, eef_quat_xyzw: np.ndarray, cube_quat_xyzw: np.ndarray) -> np.ndarray:
        """Rotation about the world z axis that lines the fingers up with the nearest cube face (or the
        operator's misaligned version of it)."""
        error = geometry.cube_yaw_error(eef_quat_xyzw, cube_quat_xyzw) + self._attempt_yaw_rad
        return geometry.rotvec_to_quat(np.array([0.0, 0.0, self.yaw_gain * error]))


class PolicyExpert:
    """Any LeRobot policy checkpoint (e.g. one of ours) as the expert: its 8-D actions in controller units."""

    def __init__(self, policy_path: str, device: str = "cpu"):
        from lerobot_bcrl.policy_runner import PolicyRunner

        self._runner = PolicyRunner(policy_path, device)

    @property
    def obs_type(self) -> str:
        return self._runner.obs_type

    def reset(self) -> None:
        self._runner.reset()

    def act(self, observation: dict) -> np.ndarray:
        controller_action, _ = controller.delta_action_to_controller(self._runner.delta_action(observation))
        return controller_action
