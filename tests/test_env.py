"""The Lift env: gymnasium API, observations, sparse reward, seeding, LeRobot EnvConfig."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from dataset_tools.experts import ScriptedLiftExpert
from lerobot_bcrl.envs.lift import LiftEnv
from lerobot_bcrl.features import (CAMERA_NAME, ENV_STATE_CUBE_POS, ENV_STATE_DIM, ENV_STATE_EEF_TO_CUBE, LIFT_REWARD,
                                    STATE_DIM, STATE_EEF_POS)
from lerobot_bcrl.rl.ppo import ANALYSIS_SEED_OFFSET
from policy_fixtures import image_dataset_root, lowdim_dataset_root, save_untrained_checkpoint  # noqa: F401

NO_OP = np.array([0, 0, 0, 0, 0, 0, 1.0, -1.0])


@pytest.fixture(scope="module")
def lowdim_env():
    env = LiftEnv(obs_type="agent_pos")
    yield env
    env.close()


def test_gymnasium_env_checker():
    env = LiftEnv(obs_type="agent_pos", horizon=20)
    check_env(env, skip_render_check=True)


def test_pixels_observation_and_render():
    env = LiftEnv(obs_type="pixels_agent_pos", image_size=96, render_size=96)
    obs, info = env.reset(seed=3)
    assert set(obs) == {"pixels", "agent_pos", "environment_state"}
    pixels = obs["pixels"][CAMERA_NAME]
    assert pixels.shape == (96, 96, 3) and pixels.dtype == np.uint8
    assert env.observation_space.contains(obs)
    assert pixels.std() > 10  # a real scene, not a blank frame
    # the red cube is visible: some pixels are clearly red
    rgb = pixels.astype(int)
    red = (rgb[..., 0] > rgb[..., 1] + 60) & (rgb[..., 0] > rgb[..., 2] + 60)
    assert red.sum() > 5
    obs2, *_ = env.step(NO_OP)
    assert env.render() is obs2["pixels"][CAMERA_NAME]  # rendered once per control step, reused
    env.close()


def test_observation_layout(lowdim_env):
    obs, _ = lowdim_env.reset(seed=0)
    assert obs["agent_pos"].shape == (STATE_DIM,) and obs["agent_pos"].dtype == np.float32
    assert obs["environment_state"].shape == (ENV_STATE_DIM,)
    eef_pos, eef_quat = obs["agent_pos"][:3], obs["agent_pos"][3:7]
    cube_pos = obs["environment_state"][:3]
    assert abs(np.linalg.norm(eef_quat) - 1) < 1e-4
    np.testing.assert_allclose(obs["environment_state"][ENV_STATE_EEF_TO_CUBE], cube_pos - eef_pos, atol=1e-6)
    assert 0.8 < cube_pos[2] < 0.85  # on the table (top at 0.8 m)


def test_environment_state_ends_with_the_cube_yaw_relative_to_the_fingers(lowdim_env):
    from lerobot_bcrl import geometry
    from lerobot_bcrl.features import ENV_STATE_CUBE_QUAT, ENV_STATE_NAMES, STATE_EEF_QUAT

    assert ENV_STATE_NAMES[-3:] == ["cube_yaw_to_fingers_sin4", "cube_yaw_to_fingers_cos4", "cube_yaw_to_fingers_turn"]
    turns = []
    for seed in range(6):  # robosuite draws the cube's yaw at every reset
        obs, _ = lowdim_env.reset(seed=seed)
        for _ in range(3):
            turn = geometry.cube_yaw_error(obs["agent_pos"][STATE_EEF_QUAT], obs["environment_state"][ENV_STATE_CUBE_QUAT])
            expected = [np.sin(4 * turn), np.cos(4 * turn), turn / (np.pi / 4)]
            np.testing.assert_allclose(obs["environment_state"][-3:], expected, rtol=1e-4, atol=1e-4)
            turns.append(turn)
            obs, *_ = lowdim_env.step(np.array([0, 0, 0, 0, 0, np.sin(np.pi / 80), np.cos(np.pi / 80), -1.0]))
    assert np.ptp(turns) > 0.3  # the feature varies with the cube, it is not a constant


def test_signed_turn_tells_plus_from_minus_45_degrees_where_sin_cos_cannot():
    import math

    from lerobot_bcrl import geometry
    from lerobot_bcrl.envs.lift import cube_yaw_features

    fingers = np.array(geometry.IDENTITY_QUAT_XYZW)  # yaw 0
    near_plus, near_minus = (cube_yaw_features(fingers, geometry.rotvec_to_quat([0.0, 0.0, math.radians(deg)]))
                             for deg in (44.0, 46.0))  # 46 degrees is -44 to the nearest face
    np.testing.assert_allclose([near_plus[2], near_minus[2]], [44 / 45, -44 / 45], rtol=1e-6)
    assert np.linalg.norm(near_plus[:2] - near_minus[:2]) < 0.15  # (sin 4d, cos 4d): nearly alike


def test_seeding_reproduces_episodes(lowdim_env):
    def run(seed):
        obs, _ = lowdim_env.reset(seed=seed)
        trajectory = [obs["environment_state"].copy()]
        rng = np.random.default_rng(0)
        for _ in range(10):
            action = NO_OP.copy()
            action[:3] = rng.uniform(-0.02, 0.02, 3)
            obs, *_ = lowdim_env.step(action)
            trajectory.append(np.concatenate([obs["agent_pos"], obs["environment_state"]]))
        return trajectory

    a, b, c = run(11), run(11), run(12)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a[0][:3], c[0][:3])  # another seed places the cube elsewhere


def test_actions_move_the_end_effector_in_the_commanded_direction(lowdim_env):
    # robosuite's OSC re-plans from the measured pose every step, so it covers only part of each
    # commanded delta (about a quarter at its default gains); direction and sign must be right.
    from lerobot_bcrl import geometry as G

    obs, _ = lowdim_env.reset(seed=0)
    start_pos = obs["agent_pos"][:3].copy()
    for _ in range(10):
        obs, *_ = lowdim_env.step(np.array([0, 0, 0.01, 0, 0, 0, 1.0, -1.0]))  # 1 cm up per step
    moved = obs["agent_pos"][:3] - start_pos
    assert 0.015 < moved[2] < 0.11 and np.all(np.abs(moved[:2]) < 0.3 * moved[2])
    yaw_step = np.concatenate([[0, 0, 0], G.rotvec_to_quat(np.array([0, 0, 0.05])), [-1.0]])
    quat_before = obs["agent_pos"][3:7].copy()
    for _ in range(10):
        obs, *_ = lowdim_env.step(yaw_step)
    rotvec = G.quat_to_rotvec(G.quat_multiply(obs["agent_pos"][3:7], G.quat_conjugate(quat_before)))
    assert rotvec[2] > 0.05 and np.all(np.abs(rotvec[:2]) < 0.3 * rotvec[2])


def test_sparse_reward_is_2_25_per_lifted_step():
    env = LiftEnv(obs_type="agent_pos", horizon=120)
    expert = ScriptedLiftExpert()
    from lerobot_bcrl.envs.controller import controller_to_delta_action

    obs, _ = env.reset(seed=5)
    expert.reset()
    rewards, lifted = [], []
    done = False
    while not done:
        action, _ = controller_to_delta_action(expert.act(obs))
        obs, reward, terminated, truncated, info = env.step(action)
        rewards.append(reward)
        lifted.append(info["is_success"])
        done = terminated or truncated
    rewards, lifted = np.array(rewards), np.array(lifted)
    assert len(rewards) == 120  # truncated at the horizon, not terminated on success
    assert lifted.any() and not lifted[0]
    np.testing.assert_array_equal(rewards, np.where(lifted, LIFT_REWARD, 0.0))
    env.close()


@pytest.mark.slow
def test_scripted_expert_success_rate():
    env = LiftEnv(obs_type="agent_pos", terminate_on_success=True)
    expert = ScriptedLiftExpert()
    from lerobot_bcrl.envs.controller import controller_to_delta_action

    successes = 0
    n = 20
    for seed in range(100, 100 + n):
        obs, _ = env.reset(seed=seed)
        expert.reset()
        done = False
        while not done:
            action, _ = controller_to_delta_action(expert.act(obs))
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        successes += info["is_success"]
    env.close()
    assert successes / n >= 0.95, f"scripted expert lifted the cube in {successes}/{n} episodes"


def test_lerobot_env_config_builds_vector_env():
    from lerobot.envs.factory import make_env_config
    from lerobot.envs.utils import env_to_policy_features

    import lerobot_bcrl  # noqa: F401  (registers the env type)

    cfg = make_env_config("bcrl_lift", obs_type="agent_pos", episode_length=5)
    features = env_to_policy_features(cfg)
    assert set(features) == {"action", "observation.state", "observation.environment_state"}
    image_cfg = make_env_config("bcrl_lift")
    assert env_to_policy_features(image_cfg)[f"observation.images.{CAMERA_NAME}"].shape == (3, 128, 128)

    envs = cfg.create_envs(n_envs=2)
    vec = envs["bcrl_lift"][0]
    assert vec.call("_max_episode_steps")[0] == 5
    obs, _ = vec.reset(seed=[0, 1])
    assert obs["agent_pos"].shape == (2, STATE_DIM)
    for _ in range(5):
        obs, reward, terminated, truncated, info = vec.step(np.tile(NO_OP, (2, 1)))
    assert truncated.all() and "is_success" in info
    vec.close()


@pytest.mark.slow
def test_async_vector_env_in_forkserver_workers():
    """lerobot-eval's default on many-core machines: AsyncVectorEnv with forkserver workers."""
    from lerobot.envs.factory import make_env_config

    import lerobot_bcrl  # noqa: F401

    cfg = make_env_config("bcrl_lift", obs_type="agent_pos", episode_length=3)
    vec = cfg.create_envs(n_envs=2, use_async_envs=True)["bcrl_lift"][0]
    assert isinstance(vec, gym.vector.AsyncVectorEnv)
    obs, _ = vec.reset(seed=[0, 0])
    np.testing.assert_array_equal(obs["environment_state"][0], obs["environment_state"][1])
    obs, reward, terminated, truncated, info = vec.step(np.tile(NO_OP, (2, 1)))
    assert obs["agent_pos"].shape == (2, STATE_DIM) and reward.shape == (2,)
    vec.close()


def load_failure_modes_script():
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "failure_modes", Path(__file__).resolve().parents[1] / "scripts" / "failure_modes.py")
    failure_modes = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(failure_modes)
    return failure_modes


def test_failure_modes_script_counts_closings_and_measures_from_the_cube():
    """scripts/failure_modes.py's episode description, with actions we choose: the arm holds still, the gripper
    closes twice; the nearest approach is the start's end-effector-to-cube distance, computed here from the poses."""
    failure_modes = load_failure_modes_script()

    gripper = [1.0, 1.0, -1.0, -1.0, 1.0, -1.0, -1.0, -1.0]  # > 0 closes: two closings

    class StillArm:
        def reset(self):
            self.t = 0

        def delta_action(self, obs):
            action = NO_OP.copy()
            action[-1] = gripper[self.t]
            self.t += 1
            return action

    env = LiftEnv(obs_type="agent_pos", horizon=len(gripper))
    try:
        obs, _ = env.reset(seed=ANALYSIS_SEED_OFFSET)
        cube_pos, eef_pos = obs["environment_state"][ENV_STATE_CUBE_POS], obs["agent_pos"][STATE_EEF_POS]
        start_distance_cm = 100 * np.linalg.norm(cube_pos - eef_pos)
        episode = failure_modes.describe_episode(StillArm(), env, ANALYSIS_SEED_OFFSET)
    finally:
        env.close()
    assert episode["lifted"] is False and episode["closings"] == 2
    assert episode["nearest_cm"] == pytest.approx(start_distance_cm, rel=0.05)
    assert episode["final_distance_cm"] == pytest.approx(start_distance_cm, rel=0.05)
    assert episode["cube_rose_cm"] < 0.2 and episode["cube_slid_cm"] < 0.2


def test_failure_modes_script_rolls_an_image_policy_out_on_the_camera(tmp_path, lowdim_dataset_root,  # noqa: F811
                                                                      image_dataset_root):  # noqa: F811
    """An image checkpoint gets the camera (a low-dim env has no frame for it to read) and a low-dim one does not;
    the image policy's episode is still described from the simulator's state."""
    from lerobot_bcrl.policy_runner import PolicyRunner

    failure_modes = load_failure_modes_script()
    save_untrained_checkpoint(lowdim_dataset_root, tmp_path / "lowdim")
    save_untrained_checkpoint(image_dataset_root, tmp_path / "images")
    assert PolicyRunner(str(tmp_path / "lowdim")).obs_type == "agent_pos"
    runner = PolicyRunner(str(tmp_path / "images"))
    assert runner.obs_type == "pixels_agent_pos"
    env = LiftEnv(obs_type=runner.obs_type, horizon=3)
    try:
        episode = failure_modes.describe_episode(runner, env, ANALYSIS_SEED_OFFSET)
    finally:
        env.close()
    assert episode["seed"] == ANALYSIS_SEED_OFFSET and episode["lifted"] is False
    assert 0 < episode["nearest_cm"] <= episode["final_distance_cm"] + 1e-9


def test_expert_speed_script_lifts_sooner_with_faster_knobs_and_its_return_counts_the_lifted_steps(
        tmp_path, lowdim_dataset_root):  # noqa: F811
    """scripts/expert_speed.py on two fresh seeds: the plain expert and one that closes in 3 steps from a lower
    hover at twice the gain; the sparse return is 2.25 for each step from the lift to the horizon (the cube held);
    the first command to close comes before the lift. Then a policy checkpoint through the same path."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "expert_speed.py"

    def run(*knobs: str) -> dict:
        out = subprocess.run([sys.executable, str(script), "--episodes=2", *knobs], capture_output=True, text=True,
                             check=True, timeout=300, cwd=script.parents[1])
        return json.loads(out.stdout.strip().splitlines()[-1])

    plain, fast = run(), run("--close_steps=3", "--position_gain=4", "--hover_height_m=0.04")
    assert plain["close_steps"] == 8 and fast["close_steps"] == 3
    assert plain["success"] == fast["success"] == 1.0
    assert fast["steps_to_lift"] < plain["steps_to_lift"] < 200
    for result in (plain, fast):
        assert result["return"] == pytest.approx(2.25 * (200 - result["steps_to_lift"] + 1), rel=0.05)
        assert 0 < result["first_close_step"] < result["steps_to_lift"]
    # the fast expert closes in 3 steps instead of 8: less time from the first closing command to the lift
    assert fast["steps_to_lift"] - fast["first_close_step"] < plain["steps_to_lift"] - plain["first_close_step"]

    # a policy instead of the expert: an untrained one, through bcrl-record's path for a learned expert
    checkpoint = tmp_path / "pretrained_model"
    save_untrained_checkpoint(lowdim_dataset_root, checkpoint)
    untrained = run("--episodes=1", f"--policy={checkpoint}")
    assert untrained["policy"] == str(checkpoint) and "close_steps" not in untrained
    assert untrained["success"] in (0.0, 1.0) and untrained["return"] >= 0.0
    if untrained["success"] == 0.0:
        assert untrained["steps_to_lift"] is None and untrained["first_close_step"] is None
