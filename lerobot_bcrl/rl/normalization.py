"""PPO's optional normalisations: rewards by the running std of the discounted return, observations by
running mean/std statistics (CleanRL's NormalizeReward / NormalizeObservation).

Observation statistics live where LeRobot keeps them, in the policy preprocessor's normaliser, so a saved
checkpoint carries the statistics it was trained with and `lerobot-eval` normalises the same way.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from lerobot.configs.types import FeatureType, NormalizationMode
from lerobot.processor.normalize_processor import NormalizerProcessorStep
from torch import Tensor

OBS_NORMALIZATION_MODES = ("dataset", "running")
RUNNING_FEATURE_TYPES = (FeatureType.STATE, FeatureType.ENV)  # images keep the dataset's per-channel stats


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


# ---------------------------------------------------------------------------------- observation stats
def find_normalizer(preprocessor) -> NormalizerProcessorStep:
    for step in preprocessor.steps:
        if isinstance(step, NormalizerProcessorStep):
            return step
    raise ValueError("the policy preprocessor has no NormalizerProcessorStep (normalizer_processor)")


def low_dim_observation_keys(normalizer: NormalizerProcessorStep) -> list[str]:
    """The state-like observation features the normaliser scales by mean/std (what running stats can track)."""
    return [key for key, feature in normalizer.features.items()
            if feature.type in RUNNING_FEATURE_TYPES and normalizer.norm_map.get(feature.type) == NormalizationMode.MEAN_STD
            and key in normalizer.stats]


def read_observation_stats(normalizer: NormalizerProcessorStep) -> dict[str, Tensor]:
    """{'<feature>.mean' / '<feature>.std': tensor} of the low-dim features: what rollout workers need."""
    return {f"{key}.{stat}": torch.as_tensor(np.asarray(normalizer.stats[key][stat]), dtype=torch.float32)
            for key in low_dim_observation_keys(normalizer) for stat in ("mean", "std")}


def write_observation_stats(normalizer: NormalizerProcessorStep, flat_stats: dict[str, Tensor]) -> None:
    """Set mean/std of some features in place (the step recomputes the tensors it normalises with)."""
    for flat_key, value in flat_stats.items():
        key, stat = flat_key.rsplit(".", 1)
        normalizer.stats[key][stat] = np.asarray(value, dtype=np.float32)
    normalizer.to(device=normalizer.device)


class RunningObservationStats:
    """`--ppo.obs_normalization=running`: mean/std of the low-dim observation features follow the rollouts.

    They start from the dataset's statistics, weighted as `prior_count` samples (the BC policy was trained
    with them), and every rollout's observations are merged in; `apply()` writes them into the normaliser.
    """

    def __init__(self, normalizer: NormalizerProcessorStep, prior_count: float):
        self.normalizer = normalizer
        keys = low_dim_observation_keys(normalizer)
        if not keys:
            raise ValueError(
                "--ppo.obs_normalization=running needs state features normalised by MEAN_STD; the policy's "
                f"normalization_mapping gives {dict(normalizer.norm_map)}")
        self.stats = {key: RunningMeanStd(np.asarray(normalizer.stats[key]["mean"]),
                                          np.asarray(normalizer.stats[key]["std"]) ** 2, prior_count)
                      for key in keys}

    def update(self, observations: dict[str, Tensor]) -> None:
        """`observations`: LeRobot observation tensors before normalisation, (B, D) per feature."""
        for key, stats in self.stats.items():
            stats.update(observations[key].reshape(observations[key].shape[0], -1).double().numpy())

    def apply(self) -> None:
        write_observation_stats(self.normalizer, {
            **{f"{key}.mean": torch.as_tensor(s.mean) for key, s in self.stats.items()},
            **{f"{key}.std": torch.as_tensor(np.sqrt(s.var)) for key, s in self.stats.items()},
        })

    def state_dict(self) -> dict:
        return {key: stats.state_dict() for key, stats in self.stats.items()}

    def load_state_dict(self, state: dict) -> None:
        self.stats = {key: RunningMeanStd.from_state_dict(value) for key, value in state.items()}
        self.apply()
