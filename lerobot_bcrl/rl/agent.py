"""The policy as PPO sees it: raw env observations in, sampled actions, log-probs and values out.

`BCRLAgent` adapts a `bcrl` policy plus its LeRobot preprocessor; any object with the same methods (a tiny
MLP in the tests) runs through the same rollout workers and PPO update.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from torch import Tensor, nn


class Agent(Protocol):
    module: nn.Module  # the parameters PPO optimises and the rollout workers receive

    def observation_batch(self, raw_obs: dict[str, np.ndarray]) -> dict[str, Tensor]: ...
    def sample(self, obs: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]: ...  # actions, log_prob, value
    def mean_action(self, obs: dict[str, Tensor]) -> Tensor: ...
    def value(self, obs: dict[str, Tensor]) -> Tensor: ...
    def evaluate(self, obs: dict[str, Tensor], actions: Tensor) -> tuple[Tensor, Tensor, Tensor]: ...


def flatten_observation(obs) -> dict[str, np.ndarray]:
    """Nested gym observation -> flat dict ('pixels.agentview'); a bare array becomes {'obs': array}."""
    if not isinstance(obs, dict):
        return {"obs": np.asarray(obs)}
    flat = {}
    for key, value in obs.items():
        if isinstance(value, dict):
            flat.update({f"{key}.{sub}": v for sub, v in flatten_observation(value).items()})
        else:
            flat[key] = np.asarray(value)
    return flat


def unflatten_observation(flat: dict[str, np.ndarray]) -> dict:
    nested: dict = {}
    for key, value in flat.items():
        head, _, tail = key.partition(".")
        if tail:
            nested.setdefault(head, {})[tail] = value
        else:
            nested[key] = value
    return nested


class BCRLAgent:
    """A `bcrl` policy and its preprocessor (normalisation with the stats saved beside the weights)."""

    def __init__(self, policy, preprocessor):
        self.policy = policy
        self.module = policy
        self.preprocessor = preprocessor

    @classmethod
    def from_pretrained(cls, pretrained_dir: str | Path) -> BCRLAgent:
        from lerobot.policies.factory import make_pre_post_processors

        from lerobot_bcrl.policies.bcrl.modeling_bcrl import BCRLPolicy

        policy = BCRLPolicy.from_pretrained(str(pretrained_dir))
        policy.config.device = "cpu"
        preprocessor, _ = make_pre_post_processors(
            policy.config, pretrained_path=str(pretrained_dir),
            preprocessor_overrides={"device_processor": {"device": "cpu"}},
        )
        return cls(policy.to("cpu"), preprocessor)

    def observation_batch(self, raw_obs: dict[str, np.ndarray]) -> dict[str, Tensor]:
        from lerobot.envs.utils import preprocess_observation

        return self.preprocessor(preprocess_observation(unflatten_observation(raw_obs)))

    def sample(self, obs):
        return self.policy.sample_actions(obs)

    def mean_action(self, obs):
        return self.policy.select_action(obs, sample=False)

    def value(self, obs):
        return self.policy.model(obs).value

    def evaluate(self, obs, actions):
        return self.policy.evaluate_actions(obs, actions)
