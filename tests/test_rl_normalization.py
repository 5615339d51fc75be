"""Observation statistics for `--ppo.obs_normalization=running`: the running mean/std is exact, lives in the
policy preprocessor's normaliser (what checkpoints save and lerobot-eval uses), and reaches rollout workers
with the weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from policy_fixtures import load_dataset, lowdim_dataset_root, make_bcrl_policy  # noqa: F401

from lerobot_bcrl.rl.agent import BCRLAgent
from lerobot_bcrl.rl.normalization import RunningMeanStd, RunningObservationStats, find_normalizer


def test_running_mean_std_matches_numpy_over_all_batches():
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, size=(n, 4)) for n in (7, 50, 1, 300)]
    stats = RunningMeanStd(np.zeros(4), np.ones(4), count=1e-9)  # a negligible prior
    for batch in batches:
        stats.update(batch)
    everything = np.concatenate(batches)
    np.testing.assert_allclose(stats.mean, everything.mean(0), rtol=1e-6)
    np.testing.assert_allclose(stats.var, everything.var(0), rtol=1e-6)
    assert stats.count == pytest.approx(len(everything))


def test_running_stats_weigh_the_dataset_prior_and_reach_the_normaliser(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    normalizer = find_normalizer(preprocessor)
    prior_mean = np.asarray(normalizer.stats["observation.state"]["mean"], np.float64)
    prior_var = np.asarray(normalizer.stats["observation.state"]["std"], np.float64) ** 2
    running = RunningObservationStats(normalizer, prior_count=100)
    assert set(running.stats) == {"observation.state", "observation.environment_state"}

    rollout_state = torch.randn(300, prior_mean.shape[0], dtype=torch.float64) * 0.5 + 2.0
    rollout_env = torch.randn(300, running.stats["observation.environment_state"].mean.shape[0], dtype=torch.float64)
    running.update({"observation.state": rollout_state, "observation.environment_state": rollout_env})
    running.apply()

    # Chan's merge of 100 prior samples (dataset mean/var) with the 300 rollout samples, by hand:
    batch_mean, batch_var = rollout_state.mean(0).numpy(), rollout_state.var(0, unbiased=False).numpy()
    delta = batch_mean - prior_mean
    mean = prior_mean + delta * 300 / 400
    var = (prior_var * 100 + batch_var * 300 + delta**2 * 100 * 300 / 400) / 400
    np.testing.assert_allclose(running.stats["observation.state"].mean, mean, rtol=1e-6)
    # the preprocessor now normalises with the new statistics
    agent = BCRLAgent(policy, preprocessor)
    x = rollout_state[:1].float()
    normalised = agent.preprocessor({"observation.state": x, "observation.environment_state": rollout_env[:1].float()})
    expected = (x.numpy() - mean) / (np.sqrt(var) + normalizer.eps)
    np.testing.assert_allclose(normalised["observation.state"].numpy(), expected, rtol=1e-4, atol=1e-5)


def test_agent_state_dict_carries_observation_stats_to_another_agent(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    learner = BCRLAgent(*make_bcrl_policy(dataset)[:2])
    worker = BCRLAgent(*make_bcrl_policy(dataset)[:2])
    running = RunningObservationStats(find_normalizer(learner.preprocessor), prior_count=1)
    state_dim = running.stats["observation.state"].mean.shape[0]
    env_dim = running.stats["observation.environment_state"].mean.shape[0]
    running.update({"observation.state": torch.full((1000, state_dim), 5.0, dtype=torch.float64),
                    "observation.environment_state": torch.full((1000, env_dim), -5.0, dtype=torch.float64)})
    running.apply()
    raw = {"agent_pos": np.full((1, state_dim), 5.0, np.float32), "environment_state": np.zeros((1, env_dim), np.float32)}
    assert not torch.allclose(worker.observation_batch(raw)["observation.state"],
                              learner.observation_batch(raw)["observation.state"])
    state = learner.state_dict()
    assert "normalizer.observation.state.mean" in state and "normalizer.observation.state.std" in state
    worker.load_state_dict(state)
    torch.testing.assert_close(worker.observation_batch(raw)["observation.state"],
                               learner.observation_batch(raw)["observation.state"])
    # mean ~5 (1000 samples of 5 beside a 1-sample prior): the state 5 normalises to ~0
    assert learner.observation_batch(raw)["observation.state"].abs().max() < 0.05
