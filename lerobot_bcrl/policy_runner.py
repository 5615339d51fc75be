"""Any LeRobot policy checkpoint acting on one gym-style observation: LeRobot's own loading, processors and
observation preprocessing, so that a policy behaves here as it does under `lerobot-eval`."""

import numpy as np


class PolicyRunner:
    """`delta_action(observation)`: the policy's 8-D action for one unbatched observation in LiftEnv's layout
    (`agent_pos`, `environment_state`, optional `pixels: {camera: HWC uint8}`)."""

    def __init__(self, policy_path: str, device: str = "cpu"):
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.envs.utils import preprocess_observation
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        self.config = PreTrainedConfig.from_pretrained(policy_path)
        self.config.device = device
        self._policy = get_policy_class(self.config.type).from_pretrained(policy_path, config=self.config)
        self._pre, self._post = make_pre_post_processors(self.config, pretrained_path=policy_path)
        self._preprocess_observation = preprocess_observation
        self._torch = torch

    @property
    def obs_type(self) -> str:
        """The LiftEnv observations the policy reads: the camera only for a policy with an image input (rendering
        costs most of a step)."""
        return "pixels_agent_pos" if self.config.image_features else "agent_pos"

    def reset(self) -> None:
        self._policy.reset()

    def delta_action(self, observation: dict) -> np.ndarray:
        batch = self._preprocess_observation(_add_batch_dim(observation))
        batch["task"] = [""]
        with self._torch.inference_mode():
            action = self._post(self._policy.select_action(self._pre(batch)))
        return action[0].cpu().numpy().astype(np.float64)


def _add_batch_dim(observation: dict) -> dict:
    return {k: _add_batch_dim(v) if isinstance(v, dict) else np.asarray(v)[None] for k, v in observation.items()}
