"""The `bcrl` network and its LeRobot policy: one model for BC (`forward`) and PPO (log-prob, entropy, value).

`CNN(image) -> spatial softmax -> keypoints`, `MLP([keypoints, state]) -> trunk`; heads off the trunk:
delta position, delta rotation, gripper logits, value; heads off the keypoints: EEF and grasp position.
With `critic_hidden_dims` set, the value has its own MLP on `[keypoints (detached), state]` instead, or, with
`critic_observation="privileged"`, on `[environment_state, state]` (an asymmetric critic for a pixels actor).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import Tensor, nn
from torch.distributions import Categorical, Normal
from torch.utils.checkpoint import checkpoint

from lerobot_bcrl.features import (
    ACTION_KEY,
    AUX_EEF_POS_KEY,
    AUX_GRASP_POS_KEY,
    AUX_GRASP_VALID_KEY,
    AUX_IMITATE_KEY,
    ENV_STATE_KEY,
    STATE_KEY,
)
from lerobot_bcrl.geometry import GRIPPER_CLOSED, GRIPPER_OPEN, MAX_DELTA_ROT_RAD
from lerobot_bcrl import rerun_log
from lerobot_bcrl.policies.bcrl import losses
from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig

GRIPPER_OPEN_CLASS, GRIPPER_CLOSED_CLASS = 0, 1
CONTINUOUS_DIM = 6  # [delta_pos / scale (3), delta_rotvec / scale (3)]: what the Gaussian is over
# A CPU's batches of 128x128 frames above this many run through the CNN in chunks: at 256 a frame's forward and
# backward took 1.4-1.5x as long as in chunks of 64; at 64, chunks of 32 gained nothing (bench/learner_throughput.py).
CPU_CHUNK_FRAMES = 64


class SpatialSoftmax(nn.Module):
    """Expected (x, y) in [-1, 1] of each channel's softmax over pixels: one keypoint per channel.

    x grows with the column, y with the row; -1 is the first pixel centre, +1 the last.
    """

    def __init__(self, learnable_temperature: bool = True, temperature: float = 1.0):
        super().__init__()
        log_temperature = torch.tensor(float(temperature)).log()
        if learnable_temperature:
            self.log_temperature = nn.Parameter(log_temperature)
        else:
            self.register_buffer("log_temperature", log_temperature)

    def forward(self, feature_map: Tensor) -> Tensor:
        batch, channels, height, width = feature_map.shape
        attention = F.softmax(feature_map.flatten(2) / self.log_temperature.exp(), dim=-1)  # (B, C, H*W)
        ys, xs = torch.meshgrid(
            torch.linspace(-1.0, 1.0, height, device=feature_map.device, dtype=feature_map.dtype),
            torch.linspace(-1.0, 1.0, width, device=feature_map.device, dtype=feature_map.dtype),
            indexing="ij",
        )
        grid_xy = torch.stack([xs.flatten(), ys.flatten()], dim=-1)  # (H*W, 2)
        return attention @ grid_xy  # (B, C, 2)


class KeypointEncoder(nn.Module):
    """Small CNN (two stride-2 convs, then stride 1) -> 1x1 conv to K maps -> spatial softmax -> (B, 2K)."""

    def __init__(self, in_channels: int, cnn_channels: tuple[int, ...], num_keypoints: int):
        super().__init__()
        layers: list[nn.Module] = []
        for i, out_channels in enumerate(cnn_channels):
            kernel, stride = (5, 2) if i == 0 else (3, 2 if i == 1 else 1)
            layers += [nn.Conv2d(in_channels, out_channels, kernel, stride, padding=kernel // 2), nn.ReLU()]
            in_channels = out_channels
        layers.append(nn.Conv2d(in_channels, num_keypoints, kernel_size=1))
        self.cnn = nn.Sequential(*layers)
        self.spatial_softmax = SpatialSoftmax()

    def forward(self, image: Tensor) -> Tensor:
        """(B, C, H, W) -> (B, 2K). On the CPU a batch above CPU_CHUNK_FRAMES frames runs through the CNN that many
        at a time, each chunk recomputed in the backward pass (activation checkpointing): the same keypoints and
        gradients, but a chunk's activations stay in the CPU's caches (docs/RESULTS.md, image BC+RL's time)."""
        if image.device.type != "cpu" or len(image) <= CPU_CHUNK_FRAMES:
            return self._keypoints(image)
        chunks = image.split(CPU_CHUNK_FRAMES)
        if not torch.is_grad_enabled():
            return torch.cat([self._keypoints(chunk) for chunk in chunks])
        return torch.cat([checkpoint(self._keypoints, chunk, use_reentrant=False) for chunk in chunks])

    def _keypoints(self, image: Tensor) -> Tensor:
        return self.spatial_softmax(self.cnn(image)).flatten(1)


def mlp(in_dim: int, hidden_dims: tuple[int, ...], out_dim: int | None = None) -> nn.Sequential:
    layers: list[nn.Module] = []
    for hidden in hidden_dims:
        layers += [nn.Linear(in_dim, hidden), nn.ReLU()]
        in_dim = hidden
    if out_dim is not None:
        layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


@dataclass
class BCRLOutputs:
    delta_pos_scaled: Tensor  # (B, 3) delta position / delta_pos_scale_m
    delta_rot_scaled: Tensor  # (B, 3) rotation vector / delta_rot_scale_rad
    gripper_logits: Tensor  # (B, 2) [open, closed]
    value: Tensor | None  # (B,) state value for PPO; None where a privileged critic lacks its input (deployment)
    eef_pos_normalized: Tensor  # (B, 3) aux head, standardized by the aux.eef_pos stats
    grasp_pos_normalized: Tensor  # (B, 3) aux head, same standardization


class BCRLModel(nn.Module):
    def __init__(self, config: BCRLConfig):
        super().__init__()
        self.config = config
        state_dim = config.input_features[STATE_KEY].shape[0]
        if config.uses_images:
            image_channels = config.image_features[config.image_key].shape[0]
            self.keypoint_encoder = KeypointEncoder(image_channels, config.cnn_channels, config.num_keypoints)
            keypoint_dim = 2 * config.num_keypoints
        else:
            self.keypoint_encoder = None
            keypoint_dim = config.input_features[ENV_STATE_KEY].shape[0]
        self.trunk = mlp(keypoint_dim + state_dim, config.trunk_hidden_dims)
        trunk_dim = config.trunk_hidden_dims[-1] if config.trunk_hidden_dims else keypoint_dim + state_dim
        self.delta_pos_head = nn.Linear(trunk_dim, 3)
        self.delta_rot_head = nn.Linear(trunk_dim, 3)
        self.gripper_head = nn.Linear(trunk_dim, 2)
        # The value: one linear layer on the trunk, or a separate critic (BCRLConfig.critic_hidden_dims). The
        # privileged critic is another module name, so that a BC checkpoint's actor-input critic is not loaded into it.
        self.value_head = self.critic = self.privileged_critic = None
        if config.critic_observation == "privileged":
            env_state_dim = config.input_features[ENV_STATE_KEY].shape[0]
            self.privileged_critic = mlp(env_state_dim + state_dim, config.critic_hidden_dims, 1)
        elif config.critic_hidden_dims:
            self.critic = mlp(keypoint_dim + state_dim, config.critic_hidden_dims, 1)
        else:
            self.value_head = nn.Linear(trunk_dim, 1)
        self.eef_pos_head = mlp(keypoint_dim, (config.aux_hidden_dim,), 3)
        self.grasp_pos_head = mlp(keypoint_dim, (config.aux_hidden_dim,), 3)

    def keypoints(self, batch: dict[str, Tensor]) -> Tensor:
        if self.keypoint_encoder is not None:
            return self.keypoint_encoder(batch[self.config.image_key])
        return batch[ENV_STATE_KEY]

    def forward(self, batch: dict[str, Tensor]) -> BCRLOutputs:
        keypoints = self.keypoints(batch)
        trunk = self.trunk(torch.cat([keypoints, batch[STATE_KEY]], dim=-1))
        return BCRLOutputs(
            delta_pos_scaled=self.delta_pos_head(trunk),
            delta_rot_scaled=self.delta_rot_head(trunk),
            gripper_logits=self.gripper_head(trunk),
            value=self.value(batch, keypoints, trunk),
            eef_pos_normalized=self.eef_pos_head(keypoints),
            grasp_pos_normalized=self.grasp_pos_head(keypoints),
        )

    def value(self, batch: dict[str, Tensor], keypoints: Tensor, trunk: Tensor) -> Tensor | None:
        if self.value_head is not None:
            return self.value_head(trunk).squeeze(-1)
        if self.critic is not None:  # keypoints detached: the value loss does not reach the CNN either
            return self.critic(torch.cat([keypoints.detach(), batch[STATE_KEY]], dim=-1)).squeeze(-1)
        if ENV_STATE_KEY not in batch:  # a robot has no privileged state, and acting needs no value
            return None
        return self.privileged_critic(torch.cat([batch[ENV_STATE_KEY], batch[STATE_KEY]], dim=-1)).squeeze(-1)


def _stat(dataset_stats: dict | None, key: str, name: str) -> Tensor | None:
    if not dataset_stats or key not in dataset_stats or name not in dataset_stats[key]:
        return None
    return torch.as_tensor(dataset_stats[key][name], dtype=torch.float32).flatten()


class BCRLPolicy(PreTrainedPolicy):
    config_class = BCRLConfig
    name = "bcrl"

    def __init__(self, config: BCRLConfig, dataset_stats: dict | None = None, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.model = BCRLModel(config)
        # Log-std of PPO's Gaussian over [delta_pos / scale, delta_rotvec / scale]; BC never trains it,
        # bcrl-finetune sets it (PPOConfig.reset_log_std) before the first update.
        self.log_std = nn.Parameter(torch.zeros(CONTINUOUS_DIM))
        # Buffers, saved in model.safetensors: a checkpoint keeps the statistics of the data it was trained on.
        self.register_buffer("gripper_class_weights", self._gripper_class_weights(dataset_stats))
        aux_mean = _stat(dataset_stats, AUX_EEF_POS_KEY, "mean")
        aux_std = _stat(dataset_stats, AUX_EEF_POS_KEY, "std")
        self.register_buffer("aux_pos_mean", aux_mean if aux_mean is not None else torch.zeros(3))
        self.register_buffer("aux_pos_std", aux_std.clamp_min(1e-3) if aux_std is not None else torch.ones(3))

    def _gripper_class_weights(self, dataset_stats: dict | None) -> Tensor:
        """Balanced weights from the closed fraction: the gripper column is -1/+1, so its mean m gives (m+1)/2."""
        action_mean = _stat(dataset_stats, ACTION_KEY, "mean")
        if action_mean is None:
            return torch.ones(2)  # no stats (e.g. built from an env config): overwritten by from_pretrained
        closed_fraction = (float(action_mean[7]) - GRIPPER_OPEN) / (GRIPPER_CLOSED - GRIPPER_OPEN)
        return losses.balanced_class_weights(closed_fraction, self.config.min_class_fraction)

    # -- LeRobot API ------------------------------------------------------------------------------------
    def get_optim_params(self):
        return self.parameters()

    def reset(self) -> None:
        pass  # no action queue and no recurrent state

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        outputs = self.model(batch)
        bc_loss, metrics = self.bc_loss(outputs, batch)
        return bc_loss, metrics

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        return self.select_action(batch, **kwargs)[:, None]

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The 8-D action (B, 8) of the mean: delta position and rotation as predicted, the likelier gripper class."""
        self.eval()
        outputs = self.model(batch)
        continuous = torch.cat([outputs.delta_pos_scaled, outputs.delta_rot_scaled], dim=-1)
        actions = self.to_env_action(continuous, outputs.gripper_logits.argmax(dim=-1))
        rerun_log.log_policy_step(actions, outputs.value)  # no-op unless our envs log rollouts to rerun
        return actions

    # -- PPO's action distribution (rl/agent.py samples and scores it) -----------------------------------
    def action_distributions(self, outputs: BCRLOutputs) -> tuple[Normal, Categorical]:
        """Gaussian over [delta_pos / scale, delta_rotvec / scale] with the learned log-std; categorical gripper."""
        mean = torch.cat([outputs.delta_pos_scaled, outputs.delta_rot_scaled], dim=-1)
        return Normal(mean, self.log_std.exp().expand_as(mean)), Categorical(logits=outputs.gripper_logits)

    # -- actions ----------------------------------------------------------------------------------------
    def to_env_action(self, continuous: Tensor, gripper_class: Tensor) -> Tensor:
        """[delta_pos (m), unit quat with qw >= 0, gripper -1/+1] from model-space values, both deltas clamped
        to the action format's limits."""
        delta_pos_m = _clamp_norm(continuous[:, :3] * self.config.delta_pos_scale_m, self.config.max_delta_pos_m)
        delta_rotvec_rad = _clamp_norm(continuous[:, 3:6] * self.config.delta_rot_scale_rad, MAX_DELTA_ROT_RAD)
        delta_quat = quat_from_rotvec(delta_rotvec_rad)
        gripper = torch.where(gripper_class == GRIPPER_CLOSED_CLASS, GRIPPER_CLOSED, GRIPPER_OPEN)
        return torch.cat([delta_pos_m, delta_quat, gripper[:, None].to(delta_pos_m.dtype)], dim=-1)

    # -- BC loss ----------------------------------------------------------------------------------------
    def bc_loss(self, outputs: BCRLOutputs, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, float]]:
        """The weighted sum of method.md section 3 and each term (unweighted) for the logs.

        Frames flagged `aux.imitate = False` (a demonstrator's planned mistake) are left out.
        """
        cfg = self.config
        if AUX_IMITATE_KEY in batch:
            keep = batch[AUX_IMITATE_KEY].reshape(-1).bool()
            if not keep.any():  # nothing to imitate in this batch: a zero loss that still has a graph
                return outputs.delta_pos_scaled.sum() * 0.0, {"bc_loss": 0.0}
            if not keep.all():
                outputs, batch = _select_rows(outputs, batch, keep)
        action = batch[ACTION_KEY]
        target_pos_scaled = action[:, :3] / cfg.delta_pos_scale_m
        target_rot_scaled = rotvec_from_quat(action[:, 3:7]) / cfg.delta_rot_scale_rad
        target_gripper_class = (action[:, 7] > 0).long()
        terms = {
            "l1": losses.l1_loss(outputs.delta_pos_scaled, target_pos_scaled),
            "l2": losses.l2_loss(outputs.delta_pos_scaled, target_pos_scaled),
            "cosine": losses.cosine_distance(outputs.delta_pos_scaled, target_pos_scaled),
            "gripper_ce": losses.gripper_cross_entropy(
                outputs.gripper_logits, target_gripper_class, self.gripper_class_weights
            ),
            "rot_l1": losses.l1_loss(outputs.delta_rot_scaled, target_rot_scaled),
            "rot_l2": losses.l2_loss(outputs.delta_rot_scaled, target_rot_scaled),
        }
        weights = {
            "l1": cfg.l1_weight,
            "l2": cfg.l2_weight,
            "cosine": cfg.cosine_weight,
            "gripper_ce": cfg.gripper_weight,
            "rot_l1": cfg.rotation_weight,
            "rot_l2": cfg.rotation_weight,
        }
        if cfg.aux_weight > 0 and (AUX_EEF_POS_KEY in batch or cfg.require_aux_targets):
            terms.update(self._aux_terms(outputs, batch))
            weights.update({"aux_eef_mse": cfg.aux_weight, "aux_grasp_mse": cfg.aux_weight})
        total = sum(weights[name] * value for name, value in terms.items())
        metrics = {f"bc_{name}": float(value.detach()) for name, value in terms.items()}
        metrics["bc_loss"] = float(total.detach())
        metrics["gripper_accuracy"] = float(
            (outputs.gripper_logits.argmax(-1) == target_gripper_class).float().mean()
        )
        return total, metrics

    def _aux_terms(self, outputs: BCRLOutputs, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        missing = [k for k in (AUX_EEF_POS_KEY, AUX_GRASP_POS_KEY, AUX_GRASP_VALID_KEY) if k not in batch]
        if missing:
            raise KeyError(
                f"bcrl: the batch lacks the auxiliary targets {missing}. They come from the dataset and must"
                " survive the preprocessor (import lerobot_bcrl: policies/bcrl/aux_targets.py keeps them), or set"
                " --policy.aux_weight=0 / --policy.require_aux_targets=false."
            )
        eef_target = (batch[AUX_EEF_POS_KEY] - self.aux_pos_mean) / self.aux_pos_std
        grasp_target = (batch[AUX_GRASP_POS_KEY] - self.aux_pos_mean) / self.aux_pos_std
        return {
            "aux_eef_mse": losses.masked_mse(outputs.eef_pos_normalized, eef_target),
            "aux_grasp_mse": losses.masked_mse(
                outputs.grasp_pos_normalized, grasp_target, batch[AUX_GRASP_VALID_KEY].bool()
            ),
        }


def _clamp_norm(vectors: Tensor, max_norm: float) -> Tensor:
    """Each row scaled down to `max_norm` where its norm exceeds it."""
    return vectors * (max_norm / vectors.norm(dim=-1, keepdim=True).clamp_min(1e-12)).clamp(max=1.0)


def rotvec_from_quat(quat_xyzw: Tensor) -> Tensor:
    """Axis-angle vectors (radians, angle in [0, pi]) of unit quaternions of either cover (geometry.quat_to_rotvec)."""
    quat_xyzw = torch.where(quat_xyzw[..., 3:4] < 0, -quat_xyzw, quat_xyzw)
    sin_half = quat_xyzw[..., :3].norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(sin_half, quat_xyzw[..., 3:4])
    # angle / sin(angle / 2) -> 2 as the angle goes to 0
    scale = torch.where(sin_half > 1e-7, angle / sin_half.clamp_min(1e-7), torch.full_like(angle, 2.0))
    return quat_xyzw[..., :3] * scale


def quat_from_rotvec(rotvec_rad: Tensor) -> Tensor:
    """Unit quaternions (xyzw, qw >= 0 for angles up to pi) of axis-angle vectors (geometry.rotvec_to_quat)."""
    angle = rotvec_rad.norm(dim=-1, keepdim=True)
    # sin(angle / 2) / angle -> 1/2 as the angle goes to 0
    scale = torch.where(angle > 1e-7, torch.sin(angle / 2.0) / angle.clamp_min(1e-7), torch.full_like(angle, 0.5))
    return torch.cat([rotvec_rad * scale, torch.cos(angle / 2.0)], dim=-1)


def _select_rows(outputs: BCRLOutputs, batch: dict, keep: Tensor) -> tuple[BCRLOutputs, dict]:
    """The rows of `outputs` and of every per-frame tensor of `batch` where `keep` is True."""
    kept_outputs = BCRLOutputs(**{f.name: None if getattr(outputs, f.name) is None else getattr(outputs, f.name)[keep]
                                  for f in fields(outputs)})
    kept_batch = {
        key: value[keep] if isinstance(value, Tensor) and value.shape[:1] == keep.shape else value
        for key, value in batch.items()
    }
    return kept_outputs, kept_batch
