"""The fast control step against robosuite's env.step: same seed, same actions -> the same trajectory.

Over whole 200-step episodes, for the scripted expert (closed loop: its actions come from the observations), its
noisy demonstrators (with a planned miss and a retry) and random actions with random gripper commands: every
`qpos`, `qvel`, observation and reward of the fast path within STATE_TOLERANCE of robosuite's.
"""

from __future__ import annotations

import numpy as np
import pytest

from dataset_tools.experts import ScriptedLiftExpert
from dataset_tools.noise import DemonstratorConfig, DemonstratorNoise
from dataset_tools.record import record_episode
from lerobot_bcrl.envs import controller
from lerobot_bcrl.envs.lift import LiftEnv

# Largest difference allowed between the two paths, in the arrays' own units (m, rad, m/s, rad/s). On the machines
# measured the paths agree bit for bit (docs/environment.md); the margin is for a platform whose numba and numpy
# link different BLAS builds.
STATE_TOLERANCE = 1e-8
HORIZON = 200


def _sim_state(env: LiftEnv) -> np.ndarray:
    data = env.sim_env.sim.data
    return np.concatenate([data.qpos, data.qvel])


def _flat(observation: dict) -> np.ndarray:
    return np.concatenate([observation["agent_pos"], observation["environment_state"]])


def _open_loop(sim_step: str, controller_actions: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    env = LiftEnv(obs_type="agent_pos", horizon=HORIZON, sim_step=sim_step)
    observation, _ = env.reset(seed=seed)
    states, observations, rewards = [_sim_state(env)], [_flat(observation)], []
    for controller_action in controller_actions:
        action, _ = controller.controller_to_delta_action(controller_action)
        observation, reward, _, _, _ = env.step(action)
        states.append(_sim_state(env))
        observations.append(_flat(observation))
        rewards.append(reward)
    env.close()
    return {"state": np.stack(states), "observation": np.stack(observations), "reward": np.array(rewards)}


def _assert_same(reference: dict[str, np.ndarray], fast: dict[str, np.ndarray]) -> None:
    for key in reference:
        assert reference[key].shape == fast[key].shape, key
        assert np.all(np.isfinite(fast[key])), key
        worst = float(np.max(np.abs(reference[key] - fast[key])))
        assert worst <= STATE_TOLERANCE, f"{key}: fast path differs from robosuite's by {worst:.3g}"


def test_random_actions_give_robosuite_trajectory():
    rng = np.random.default_rng(7)
    controller_actions = rng.uniform(-1.0, 1.0, (HORIZON, controller.CONTROLLER_ACTION_DIM))
    controller_actions[:, 6] = rng.choice([-1.0, 1.0], HORIZON)  # open/close at random
    reference = _open_loop("robosuite", controller_actions, seed=11)
    fast = _open_loop("fast", controller_actions, seed=11)
    _assert_same(reference, fast)
    # The arm went somewhere: the comparison is not between two resting arms.
    assert np.ptp(reference["state"][:, :7], axis=0).max() > 0.3


@pytest.mark.parametrize(
    ("sigma", "miss_offset_m"),
    [(0.0, None), (0.1, np.array([0.03, -0.02, 0.01]))],
    ids=["expert", "noisy-with-planned-miss"],
)
def test_expert_episode_records_the_same_frames(sigma, miss_offset_m):
    frames, stats = {}, {}
    for sim_step in ("robosuite", "fast"):
        env = LiftEnv(obs_type="agent_pos", horizon=HORIZON, sim_step=sim_step)
        noise = DemonstratorNoise(DemonstratorConfig(noise_std=sigma), controller.CONTROLLER_ACTION_DIM, [3, 1])
        frames[sim_step], stats[sim_step] = record_episode(
            env, ScriptedLiftExpert(), noise, seed=5, miss_offset_m=miss_offset_m
        )
        env.close()
    assert stats["robosuite"]["success"], "the expert lifts: the episode covers grasp and lift"
    assert stats["fast"] == stats["robosuite"]
    for key, reference in frames["robosuite"].items():
        worst = float(np.max(np.abs(reference.astype(np.float64) - frames["fast"][key].astype(np.float64))))
        # float32 frames: one unit in the last place of a value near 1 is 1.2e-7
        assert worst <= max(STATE_TOLERANCE, 2 * np.finfo(np.float32).eps * np.abs(reference).max()), key


def test_unsupported_controller_configuration_is_refused():
    from lerobot_bcrl.envs.fast_control import FastControlStep

    env = LiftEnv(obs_type="agent_pos", sim_step="robosuite")
    env.sim_env.robots[0].part_controllers["right"].input_type = "absolute"
    with pytest.raises(ValueError, match="input_type='absolute'"):
        FastControlStep(env.sim_env)
    env.close()


def test_dataset_recorded_either_way_has_the_same_frames(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from dataset_tools import record as rec

    columns = {}
    for sim_step in ("robosuite", "fast"):
        cfg = rec.RecordConfig(
            repo_id="local/fast_control", root=tmp_path / sim_step, n_episodes=2, episode_length=HORIZON, seed=3,
            sigma=0.1, images=False, sim_step=sim_step,
        )  # fmt: skip
        rec.record(cfg)
        dataset = LeRobotDataset(cfg.repo_id, root=cfg.root)
        columns[sim_step] = {
            key: np.asarray(dataset.hf_dataset[key], dtype=np.float64)
            for key, feature in dataset.features.items()
            if feature["dtype"] in ("float32", "float64", "bool", "int64")
        }
    assert columns["fast"].keys() == columns["robosuite"].keys()
    assert len(columns["fast"]["action"]) == 2 * HORIZON
    for key, reference in columns["robosuite"].items():
        worst = float(np.max(np.abs(reference - columns["fast"][key]))) if reference.size else 0.0
        # float32 columns: a value computed 1e-14 apart may round to the neighbouring float32 (1.2e-7 near 1)
        assert worst <= max(STATE_TOLERANCE, 2 * np.finfo(np.float32).eps * max(1.0, np.abs(reference).max())), key
