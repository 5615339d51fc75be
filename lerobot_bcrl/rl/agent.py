"""The policy as PPO sees it: raw env observations in, sampled actions, log-probs and values out.

`BCRLAgent` adapts a `bcrl` policy plus its LeRobot preprocessor; any object with the same methods (a tiny
MLP in the tests) runs through the same rollout workers and PPO update.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from torch import Tensor, nn

from lerobot_bcrl.features import ENV_STATE_KEY


class Agent(Protocol):
    module: nn.Module  # the parameters PPO optimises
    noise_dims: int  # the action's Gaussian part: how many standard-normal draws `sample` takes as `noise`

    def state_dict(self) -> dict[str, Tensor]: ...  # what rollout workers receive: the weights
    def load_state_dict(self, state: dict[str, Tensor]) -> None: ...

    def observation_batch(self, raw_obs: dict[str, np.ndarray]) -> dict[str, Tensor]: ...
    # actions, log_prob, value; `noise` (N, noise_dims) drives the Gaussian part (mean + std * noise), None: i.i.d.
    def sample(self, obs: dict[str, Tensor], noise: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]: ...
    def to_env_action(self, actions: Tensor) -> Tensor: ...  # what env.step gets (e.g. clamped)
    def mean_action(self, obs: dict[str, Tensor]) -> Tensor: ...  # deterministic, already an env action
    def value(self, obs: dict[str, Tensor]) -> Tensor: ...
    # log_prob, entropy per action part ({"action": ...}, or e.g. {"continuous": ..., "gripper": ...}), value
    def evaluate(self, obs: dict[str, Tensor], actions: Tensor) -> tuple[Tensor, dict[str, Tensor], Tensor]: ...
    # The parameters whose gradient norms PPO's `gradient_share` weighting and its logged term norms compare.
    def term_norm_parameters(self) -> list[nn.Parameter]: ...


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
        self.noise_dims = policy.log_std.shape[0]

    @classmethod
    def from_pretrained(cls, pretrained_dir: str | Path) -> BCRLAgent:
        from lerobot.policies.factory import make_pre_post_processors

        from lerobot_bcrl.policies.bcrl.modeling_bcrl import BCRLPolicy

        with contextlib.redirect_stdout(io.StringIO()):  # LeRobot prints "Loading weights ..." in every worker
            policy = BCRLPolicy.from_pretrained(str(pretrained_dir))
        policy.config.device = "cpu"
        preprocessor, _ = make_pre_post_processors(
            policy.config, pretrained_path=str(pretrained_dir),
            preprocessor_overrides={"device_processor": {"device": "cpu"}},
        )
        return cls(policy.to("cpu"), preprocessor)

    @classmethod
    def from_files(cls, files: dict[str, bytes]) -> BCRLAgent:
        """`from_pretrained` on a saved policy's files sent as bytes: a Ray node need not see the learner's disk."""
        with tempfile.TemporaryDirectory() as folder:
            for name, data in files.items():
                (Path(folder) / name).write_bytes(data)
            return cls.from_pretrained(folder)

    def state_dict(self) -> dict[str, Tensor]:
        return self.policy.state_dict()

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        self.policy.load_state_dict(state)

    def observation_batch(self, raw_obs: dict[str, np.ndarray]) -> dict[str, Tensor]:
        """Env observations as LeRobot names them ('observation.state', ...), through the policy's preprocessor."""
        from lerobot.envs.utils import preprocess_observation

        return self.preprocessor(preprocess_observation(unflatten_observation(raw_obs)))

    # PPO learns on the raw sample [delta_pos / scale, delta_rotvec / scale, gripper class]: its log-prob is exact.
    # The env gets its projection (clamped deltas, unit quaternion, -1/+1 gripper) from `to_env_action`; taking
    # log-probs at the projected point instead makes the ratio explode wherever the clamp is active.
    def sample(self, obs, noise=None):
        outputs = self.policy.model(obs)
        continuous_dist, gripper_dist = self.policy.action_distributions(outputs)
        continuous = continuous_dist.sample() if noise is None else continuous_dist.mean + continuous_dist.stddev * noise
        raw_actions = torch.cat([continuous, gripper_dist.sample()[:, None].float()], dim=-1)
        log_prob, _ = self._log_prob_and_entropy(continuous_dist, gripper_dist, raw_actions)
        return raw_actions, log_prob, self._required_value(outputs.value)

    def evaluate(self, obs, raw_actions):
        outputs = self.policy.model(obs)
        continuous_dist, gripper_dist = self.policy.action_distributions(outputs)
        log_prob, entropies = self._log_prob_and_entropy(continuous_dist, gripper_dist, raw_actions)
        return log_prob, entropies, self._required_value(outputs.value)

    @staticmethod
    def _required_value(value: Tensor | None) -> Tensor:
        """PPO needs the value; only the privileged critic can lack its input (a robot acting needs none)."""
        if value is None:
            raise ValueError(f"the policy's privileged critic reads '{ENV_STATE_KEY}', which these observations lack:"
                             " PPO needs an env that gives it (bcrl_lift does in every obs_type)")
        return value

    @staticmethod
    def _log_prob_and_entropy(continuous_dist, gripper_dist, raw_actions):
        n = continuous_dist.mean.shape[-1]  # the continuous dims, then the gripper class
        log_prob = continuous_dist.log_prob(raw_actions[:, :n]).sum(-1)
        log_prob = log_prob + gripper_dist.log_prob(raw_actions[:, n].long())
        return log_prob, {"continuous": continuous_dist.entropy().sum(-1), "gripper": gripper_dist.entropy()}

    def to_env_action(self, raw_actions):
        n = self.noise_dims
        return self.policy.to_env_action(raw_actions[:, :n], raw_actions[:, n].long())

    def mean_action(self, obs):
        return self.policy.select_action(obs)

    def term_norm_parameters(self) -> list[nn.Parameter]:
        """All but the image encoder's: the norms then take backward passes through the layers after it only, not
        two more through the CNN per minibatch (docs/RESULTS.md, image BC+RL's time). A low-dim policy has none."""
        encoder = self.policy.model.keypoint_encoder
        skipped = set() if encoder is None else {id(p) for p in encoder.parameters()}
        return [p for p in self.policy.parameters() if p.requires_grad and id(p) not in skipped]

    def value(self, obs):
        return self._required_value(self.policy.model(obs).value)
