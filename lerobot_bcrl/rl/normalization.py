"""PPO's reward normalisation: rewards divided by the running std of the discounted return (CleanRL's
NormalizeReward). Observations are normalised by the policy's own preprocessor, with the demonstrations' statistics.
"""

from __future__ import annotations

import math

import numpy as np


class RunningMeanStd:
    """Mean and variance over everything seen so far, merged batch by batch (Chan et al.'s parallel update)."""

    def __init__(self, mean: np.ndarray | float = 0.0, var: np.ndarray | float = 1.0, count: float = 1e-4):
        self.mean, self.var, self.count = np.asarray(mean, np.float64), np.asarray(var, np.float64), float(count)

    def update(self, batch: np.ndarray) -> None:
        """`batch` (B, ...): B samples of the tracked shape."""
        batch_mean, batch_var, batch_count = batch.mean(axis=0), batch.var(axis=0), batch.shape[0]
        delta, total = batch_mean - self.mean, self.count + batch_count
        self.mean = self.mean + delta * batch_count / total
        self.var = (self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total) / total
        self.count = total

    def state_dict(self) -> dict:
        return {"mean": self.mean.tolist(), "var": self.var.tolist(), "count": self.count}

    @classmethod
    def from_state_dict(cls, state: dict) -> RunningMeanStd:
        return cls(state["mean"], state["var"], state["count"])


class RewardScaler:
    """Divides rewards by the running std of each env's discounted return (state saved with checkpoints)."""

    def __init__(self, gamma: float, n_envs: int):
        self.gamma = gamma
        self.discounted_return = np.zeros(n_envs)
        self.return_stats = RunningMeanStd()

    def __call__(self, rewards: np.ndarray, dones: np.ndarray) -> np.ndarray:
        for t in range(rewards.shape[0]):
            self.discounted_return = self.discounted_return * self.gamma + rewards[t]
            self.return_stats.update(self.discounted_return.reshape(-1))
            self.discounted_return = self.discounted_return * (1 - dones[t])
        return (rewards / math.sqrt(float(self.return_stats.var) + 1e-8)).astype(np.float32)

    def state_dict(self) -> dict:
        return {"discounted_return": self.discounted_return.tolist(), **self.return_stats.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.discounted_return = np.asarray(state["discounted_return"])
        self.return_stats = RunningMeanStd.from_state_dict(state)
