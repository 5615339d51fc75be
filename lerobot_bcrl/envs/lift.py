"""robosuite Lift with the Sawyer arm as a gymnasium env with LeRobot's observation keys.

Actions are the 8-D delta layout of method.md (`lerobot_bcrl.geometry.ACTION_NAMES`); observations are
`pixels` (agentview, uint8 HWC, rendered once per control step), `agent_pos` and `environment_state`.
"""

from __future__ import annotations

import time
from typing import Any

import gymnasium as gym
import numpy as np

from lerobot_bcrl import features, geometry, rerun_log
from lerobot_bcrl.envs import controller
from lerobot_bcrl.envs.fast_control import FastControlStep
from lerobot_bcrl.envs.rendering import CameraRenderer
from lerobot_bcrl.features import CAMERA_NAME, ENV_STATE_DIM, STATE_DIM

import robosuite  # noqa: E402  (after rendering.py has set MUJOCO_GL)

TASK_DESCRIPTION = "Lift the red cube off the table."
OBS_TYPES = ("pixels_agent_pos", "agent_pos")
SIM_STEPS = ("fast", "robosuite")
# The robosuite observables _observation() reads.
OBSERVABLES = ("robot0_eef_pos", "robot0_eef_quat_site", "robot0_gripper_qpos", "robot0_joint_pos", "cube_pos", "cube_quat")


def cube_yaw_features(eef_quat_xyzw: np.ndarray, cube_quat_xyzw: np.ndarray) -> np.ndarray:
    """(sin 4d, cos 4d, d / (pi/4)), d the yaw that turns the fingers onto the nearest cube face
    (features.ENV_STATE_NAMES says why these three)."""
    turn = geometry.cube_yaw_error(eef_quat_xyzw, cube_quat_xyzw)
    return np.array([np.sin(4 * turn), np.cos(4 * turn), turn / (np.pi / 4)])


class LiftEnv(gym.Env):
    """Sawyer Lift, horizon 200 at 20 Hz, sparse reward (2.25 per lifted step) unless `dense_reward`."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        obs_type: str = "pixels_agent_pos",
        image_size: int = 128,
        cheap_render: bool = True,
        horizon: int = 200,
        control_freq: int = 20,
        dense_reward: bool = False,
        terminate_on_success: bool = False,
        render_mode: str = "rgb_array",
        render_size: int = 128,
        model_seed: int = 0,
        rerun_dir: str | None = None,
        sim_step: str = "fast",
    ):
        if obs_type not in OBS_TYPES:
            raise ValueError(f"obs_type must be one of {OBS_TYPES}, got {obs_type!r}")
        if sim_step not in SIM_STEPS:
            raise ValueError(f"sim_step must be one of {SIM_STEPS}, got {sim_step!r}")
        self.obs_type = obs_type
        self.image_size = image_size
        self.horizon = horizon
        self.terminate_on_success = terminate_on_success
        self.render_mode = render_mode
        self.render_size = render_size
        self.task_description = TASK_DESCRIPTION
        self.task = "lift"
        self.metadata = {**self.metadata, "render_fps": control_freq}

        # robosuite draws the cube's size from the global numpy RNG when it builds the model: fix it, so
        # that every env instance (recorder, evaluator, test) simulates the same cube.
        outer_state = np.random.get_state()
        np.random.seed(model_seed)
        try:
            self._sim_env = self._make_sim_env(control_freq, horizon, dense_reward)
        finally:
            np.random.set_state(outer_state)
        self._model = self._sim_env.sim.model._model
        self._data = self._sim_env.sim.data._data
        # "fast": robosuite's controller arithmetic without its per-substep Python (fast_control.py), the same
        # trajectories; "robosuite": robosuite's own env.step, the reference.
        self._fast_step = FastControlStep(self._sim_env) if sim_step == "fast" else None
        self._sensors = {name: self._sim_env._observables[name]._sensor for name in OBSERVABLES}
        self._cheap_render = cheap_render
        self._camera = (
            CameraRenderer(self._model, CAMERA_NAME, image_size, image_size, cheap=cheap_render)
            if obs_type == "pixels_agent_pos"
            else None
        )
        self._render_camera: CameraRenderer | None = None
        self._pixels: np.ndarray | None = None
        # robosuite draws cube placement and joint noise from the global numpy RNG; each env keeps its own
        # state and swaps it in around reset, so that seeding one env never disturbs another.
        self._robosuite_rng_state = np.random.RandomState().get_state()
        self._step_count = 0
        self.n_clamped_actions = 0
        self.render_s = 0.0  # seconds spent rendering the camera observation, over the env's life (timing reports)
        # Optional: one .rrd file per episode with what happened (and the policy's predictions, when the
        # policy runs in this process).
        self._rerun_dir = rerun_dir
        self._rerun_slot = rerun_log.RolloutSlot() if rerun_dir else None
        self._n_episodes = 0
        self._last_obs: dict | None = None

        spaces: dict[str, gym.Space] = {
            "agent_pos": gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32),
            "environment_state": gym.spaces.Box(-np.inf, np.inf, (ENV_STATE_DIM,), np.float32),
        }
        if self._camera is not None:
            # A dict of cameras: LeRobot maps `pixels/<cam>` to `observation.images.<cam>`.
            spaces["pixels"] = gym.spaces.Dict(
                {CAMERA_NAME: gym.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)}
            )
        self.observation_space = gym.spaces.Dict(spaces)
        low = np.array([-geometry.MAX_DELTA_POS_M] * 3 + [-1.0] * 4 + [-1.0], np.float32)
        high = np.array([geometry.MAX_DELTA_POS_M] * 3 + [1.0] * 4 + [1.0], np.float32)
        self.action_space = gym.spaces.Box(low, high, dtype=np.float32)

    @staticmethod
    def _make_sim_env(control_freq: int, horizon: int, dense_reward: bool):
        return robosuite.make(
            "Lift",
            robots="Sawyer",
            has_renderer=False,
            has_offscreen_renderer=False,
            use_camera_obs=False,
            use_object_obs=True,
            reward_scale=None,
            reward_shaping=dense_reward,
            control_freq=control_freq,
            horizon=horizon,
            ignore_done=True,  # the horizon is ours (truncation), robosuite must not refuse steps
            hard_reset=False,  # reloading the model every reset costs ~0.3 s and invalidates renderers
        )

    # -- gymnasium API ---------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._robosuite_rng_state = np.random.RandomState(seed).get_state()
        outer_state = np.random.get_state()
        np.random.set_state(self._robosuite_rng_state)
        try:
            sim_obs = self._sim_env.reset()
            if self._fast_step is not None:
                self._fast_step.reset()
        finally:
            self._robosuite_rng_state = np.random.get_state()
            np.random.set_state(outer_state)
        self._step_count = 0
        obs = self._observation(sim_obs)
        if self._rerun_slot is not None:
            self._start_rerun_episode()
            self._last_obs = obs
        return obs, {"is_success": False}

    def step(self, action: np.ndarray):
        controller_action, clamped = controller.delta_action_to_controller(action)
        self.n_clamped_actions += int(clamped)
        if self._fast_step is None:
            sim_obs, reward, _, _ = self._sim_env.step(controller_action)
        else:
            self._fast_step.step(controller_action)
            sim_obs = {name: np.array(sensor({})) for name, sensor in self._sensors.items()}
            reward = self._sim_env.reward(controller_action)
        self._step_count += 1
        is_success = bool(self._sim_env._check_success())
        terminated = self.terminate_on_success and is_success
        truncated = self._step_count >= self.horizon
        info = {"is_success": is_success, "action_clamped": clamped}
        obs = self._observation(sim_obs)
        if self._rerun_slot is not None and self._rerun_slot.logger is not None:
            self._log_rerun_step(action, reward, is_success, terminated or truncated)
            self._last_obs = obs
        return obs, float(reward), terminated, truncated, info

    def render(self) -> np.ndarray:
        if self._camera is not None and self.render_size == self.image_size and self._pixels is not None:
            return self._pixels  # already rendered this control step
        if self._render_camera is None:
            self._render_camera = CameraRenderer(
                self._model, CAMERA_NAME, self.render_size, self.render_size, cheap=self._cheap_render
            )
        return self._render_camera.render(self._data)

    def _start_rerun_episode(self) -> None:
        import os
        from pathlib import Path

        slot = self._rerun_slot
        slot.close_episode()
        path = Path(self._rerun_dir) / f"rollout_{os.getpid()}_{slot.position}_{self._n_episodes:04d}.rrd"
        slot.logger = rerun_log.EpisodeLogger(f"bcrl_lift/{path.stem}", save_path=path, fps=self.metadata["render_fps"])
        slot.frame_index = 0
        self._n_episodes += 1

    def _log_rerun_step(self, action, reward: float, is_success: bool, done: bool) -> None:
        obs, slot = self._last_obs, self._rerun_slot
        frame = {
            features.STATE_KEY: obs["agent_pos"],
            features.ENV_STATE_KEY: obs["environment_state"],
            features.ACTION_KEY: np.asarray(action, dtype=np.float32),
            features.REWARD_KEY: reward,
            features.SUCCESS_KEY: is_success,
            features.DONE_KEY: done,
        }
        if "pixels" in obs:
            frame[features.IMAGE_KEY] = obs["pixels"][CAMERA_NAME]
        slot.logger.log_step(slot.frame_index, frame)
        slot.frame_index += 1

    def close(self) -> None:
        if self._rerun_slot is not None:
            self._rerun_slot.release()
        for renderer in (self._camera, self._render_camera):
            if renderer is not None:
                renderer.close()
        self._camera = self._render_camera = None
        self._sim_env.close()

    # -- privileged access (experts, recorders, tests) --------------------------------------------------
    @property
    def sim_env(self):
        """The underlying robosuite env."""
        return self._sim_env

    @property
    def cube_lifted(self) -> bool:
        return bool(self._sim_env._check_success())

    def _observation(self, sim_obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        agent_pos = np.concatenate(
            [
                sim_obs["robot0_eef_pos"],
                sim_obs["robot0_eef_quat_site"],
                sim_obs["robot0_gripper_qpos"],
                sim_obs["robot0_joint_pos"],
            ]
        ).astype(np.float32)
        environment_state = np.concatenate(
            [
                sim_obs["cube_pos"],
                sim_obs["cube_quat"],
                sim_obs["cube_pos"] - sim_obs["robot0_eef_pos"],
                cube_yaw_features(sim_obs["robot0_eef_quat_site"], sim_obs["cube_quat"]),
            ]
        ).astype(np.float32)
        obs: dict[str, Any] = {"agent_pos": agent_pos, "environment_state": environment_state}
        if self._camera is not None:
            render_start = time.perf_counter()
            self._pixels = self._camera.render(self._data)
            self.render_s += time.perf_counter() - render_start
            obs["pixels"] = {CAMERA_NAME: self._pixels}
        return obs
