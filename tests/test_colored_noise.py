"""Colored exploration noise (rl/colored_noise.py, `--rollout.noise_color_beta`): each step N(0, 1), neighbouring
steps as correlated as beta asks, and the rollout workers drive the policy's Gaussian with one reproducible sequence
per env and episode, scored by the policy's own log-prob."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_rl_learns import MLPAgent, ReachOrigin

from lerobot_bcrl.rl.colored_noise import powerlaw_noise
from lerobot_bcrl.rl.configuration import RolloutConfig
from lerobot_bcrl.rl.rollout import NOISE_SEEDS, InlineWorkers, derived_seed

EPISODE_STEPS = 20  # ReachOrigin's
gym.register("ReachOriginTimeLimit-v0", entry_point=ReachOrigin, max_episode_steps=EPISODE_STEPS)


def lag_one_correlation(noise: np.ndarray) -> float:
    """Correlation of each step with the next, over sequences (S, T, D)."""
    return float(np.corrcoef(noise[:, :-1].ravel(), noise[:, 1:].ravel())[0, 1])


@pytest.mark.parametrize("n_steps", [200, 201])  # an even length has a Nyquist term, an odd one none
def test_powerlaw_noise_is_unit_normal_at_every_step_and_correlated_as_beta_asks(n_steps):
    rng = np.random.default_rng(0)
    lag_one = {}
    for beta in (0.0, 0.5, 1.0, 2.0):
        noise = np.stack([powerlaw_noise(beta, n_steps, 4, rng) for _ in range(250)])  # (sequences, steps, dims)
        assert noise.shape == (250, n_steps, 4) and noise.dtype == np.float32
        assert abs(noise.mean()) < 0.05 and abs(noise.std() - 1.0) < 0.03, (beta, noise.mean(), noise.std())
        # 1,000 draws per step: the first, middle and last steps are as wide as the rest
        assert np.all(np.abs(noise.std(axis=(0, 2))[[0, n_steps // 2, -1]] - 1.0) < 0.1), beta
        lag_one[beta] = lag_one_correlation(noise)
    assert abs(lag_one[0.0]) < 0.02, lag_one  # white
    assert 0.2 < lag_one[0.5] < lag_one[1.0] < lag_one[2.0], lag_one  # redder: neighbours agree more


def colored_workers(beta: float | None, seed: int = 7) -> InlineWorkers:
    """Two ReachOrigin envs with `noise_color_beta=beta` (None: the workers' default)."""
    color = {} if beta is None else {"noise_color_beta": beta}
    return InlineWorkers([{"make_env": lambda: gym.make("ReachOriginTimeLimit-v0"), "make_agent": MLPAgent,
                           "n_envs": 2, "seed": seed, **color}])


def test_workers_drive_the_gaussian_with_one_colored_sequence_per_env_and_episode():
    agent = MLPAgent()
    state = agent.module.state_dict()
    workers = colored_workers(beta=1.0)
    first, second = workers.collect(state, 30), workers.collect(state, 30)  # episodes span the two rollouts
    np.testing.assert_array_equal(first.actions, colored_workers(beta=1.0).collect(state, 30).actions)
    assert not np.array_equal(first.actions, colored_workers(beta=1.0, seed=8).collect(state, 30).actions)
    with torch.no_grad():  # the noise each action carries: (action - mean) / std, std = 1 here
        noise = [t.actions[..., 0] - agent.module["actor"](torch.as_tensor(t.observations["obs"]))[..., 0].numpy()
                 for t in (first, second)]
    noise = np.concatenate(noise)  # (60 steps, 2 envs): episodes 0, 1 and 2 of each env
    for env_index in range(2):
        for episode in range(3):
            rng = np.random.default_rng(derived_seed(7, NOISE_SEEDS, env_index, episode))
            expected = powerlaw_noise(1.0, EPISODE_STEPS, 1, rng)[:, 0]  # one sequence of the episode's length
            steps = slice(episode * EPISODE_STEPS, (episode + 1) * EPISODE_STEPS)
            np.testing.assert_allclose(noise[steps, env_index], expected, rtol=1e-5, atol=1e-5)
    # PPO's ratio starts at 1: the stored log-prob is the policy's Gaussian log-prob of the action it took
    with torch.no_grad():
        log_prob, _, _ = agent.evaluate({"obs": torch.as_tensor(first.observations["obs"].reshape(-1, 1))},
                                        torch.as_tensor(first.actions.reshape(-1, 1)))
    np.testing.assert_allclose(log_prob.numpy(), first.log_probs.reshape(-1), rtol=1e-5, atol=1e-5)


def test_white_noise_is_the_default_and_a_negative_beta_is_refused():
    state = MLPAgent().module.state_dict()
    default = colored_workers(beta=None).collect(state, 30)
    np.testing.assert_array_equal(default.actions, colored_workers(beta=0.0).collect(state, 30).actions)
    assert not np.array_equal(default.actions, colored_workers(beta=0.5).collect(state, 30).actions)
    with pytest.raises(ValueError, match="noise_color_beta"):
        RolloutConfig(noise_color_beta=-0.5)
