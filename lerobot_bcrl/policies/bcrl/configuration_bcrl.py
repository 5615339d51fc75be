"""The `bcrl` policy configuration: network sizes and BC loss weights.

Registered with LeRobot as `--policy.type=bcrl`; serialized as `config.json` beside the weights.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode
from lerobot.configs.policies import PreTrainedConfig
from lerobot.optim.optimizers import AdamWConfig

from lerobot_bcrl.features import ENV_STATE_KEY, STATE_KEY
from lerobot_bcrl.geometry import ACTION_DIM, MAX_DELTA_POS_M, MAX_DELTA_ROT_RAD

OBSERVATION_MODES = ("auto", "pixels", "low_dim")
CRITIC_OBSERVATIONS = ("actor", "privileged")


@PreTrainedConfig.register_subclass("bcrl")
@dataclass
class BCRLConfig(PreTrainedConfig):
    # "pixels": CNN on the camera + observation.state; "low_dim": observation.environment_state +
    # observation.state, no CNN; "auto": pixels when the features hold a camera, low_dim otherwise.
    observation_mode: str = "auto"
    # Nothing is pushed to a hub unless asked (LeRobot's default is True, which also demands a repo_id).
    push_to_hub: bool = False

    # -- network ---------------------------------------------------------------------------------------
    cnn_channels: tuple[int, ...] = (16, 32, 32)  # conv widths; the first two convs have stride 2
    num_keypoints: int = 32  # spatial-softmax keypoints (each gives an (x, y) pair)
    trunk_hidden_dims: tuple[int, ...] = (256, 256)  # MLP([keypoints | env_state, state]) -> trunk
    # (): the value is one linear layer on the shared trunk (the paper's network). Hidden widths, e.g.
    # (256, 256): a separate critic MLP on the trunk's inputs (keypoints detached), so that PPO's value loss
    # cannot pull the trunk away from what the BC term taught it. A BC checkpoint without a critic loads with
    # a freshly initialised one (`bcrl-finetune --policy.path=... --policy.critic_hidden_dims=[256,256]`).
    critic_hidden_dims: tuple[int, ...] = ()
    # What that separate critic reads. "actor": the actor's inputs, as above. "privileged" (pixels policies): its
    # own MLP on observation.environment_state + observation.state, which the simulator gives and a robot does not:
    # an asymmetric critic. Only PPO in simulation uses the value; `select_action` works without the
    # environment state, so deployment needs the actor alone.
    critic_observation: str = "actor"
    aux_hidden_dim: int = 64  # hidden width of the EEF- and grasp-position heads off the keypoints
    # The delta-position head predicts delta_pos / delta_pos_scale_m, so that its targets are O(1)
    # although the action itself is left unnormalized (ACTION uses IDENTITY, see normalization_mapping).
    delta_pos_scale_m: float = MAX_DELTA_POS_M
    max_delta_pos_m: float = MAX_DELTA_POS_M  # select_action clamps |delta_pos| to this (paper's range)
    # The rotation head predicts the delta's rotation vector / delta_rot_scale_rad (O(1) like the position's);
    # the action itself stays a unit quaternion, clamped to the format's pi/40 (geometry.MAX_DELTA_ROT_RAD).
    delta_rot_scale_rad: float = MAX_DELTA_ROT_RAD

    # -- BC loss weights (method.md section 3) ----------------------------------------------------------
    l1_weight: float = 1.0  # L1 on delta_pos / delta_pos_scale_m
    l2_weight: float = 1.0  # L2 (MSE) on delta_pos / delta_pos_scale_m
    cosine_weight: float = 1.0  # 1 - cos(delta_pos_hat, delta_pos): direction, in [0, 2]
    gripper_weight: float = 1.0  # class-weighted cross entropy on the gripper class
    # L1 + L2 on the rotation vector / delta_rot_scale_rad, each weighted by this: the rotation target is scaled
    # like the position's, so both have comparable size with weights near 1 (docs/RESULTS.md#rotation-target).
    rotation_weight: float = 1.0
    aux_weight: float = 0.1  # EEF-position MSE + grasp-position MSE (masked by aux.grasp_valid)
    # Gripper class weights come from the dataset's closed fraction; clip it so that a dataset that
    # (almost) never closes the gripper cannot produce an infinite weight.
    min_class_fraction: float = 0.01
    # lerobot-train always gives aux.* (aux_targets.py keeps them); a batch without them fails loudly
    # unless this is False, so that a broken pipeline never silently trains without the aux heads.
    require_aux_targets: bool = True

    # -- optimizer (AdamW with weight decay, the paper's choice) ----------------------------------------
    optimizer_lr: float = 3e-4
    optimizer_weight_decay: float = 1e-4
    optimizer_betas: tuple[float, float] = (0.9, 0.999)
    optimizer_grad_clip_norm: float = 10.0

    # Images in [0,1] and states are standardized by the preprocessor. ACTION is IDENTITY: the unit
    # quaternion and the gripper class must leave the postprocessor exact; delta_pos and the rotation are
    # scaled inside the model instead (delta_pos_scale_m, delta_rot_scale_rad).
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MEAN_STD,
            "ENV": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )

    def __post_init__(self):
        super().__post_init__()
        if self.observation_mode not in OBSERVATION_MODES:
            raise ValueError(f"observation_mode must be one of {OBSERVATION_MODES}, got {self.observation_mode!r}")
        if self.critic_observation not in CRITIC_OBSERVATIONS:
            raise ValueError(f"critic_observation must be one of {CRITIC_OBSERVATIONS}, got {self.critic_observation!r}")
        if self.critic_observation == "privileged" and not self.critic_hidden_dims:
            raise ValueError("critic_observation='privileged' is a separate critic: give critic_hidden_dims, e.g. [256, 256]")
        if self.delta_pos_scale_m <= 0:
            raise ValueError(f"delta_pos_scale_m must be > 0, got {self.delta_pos_scale_m}")
        if self.delta_rot_scale_rad <= 0:
            raise ValueError(f"delta_rot_scale_rad must be > 0, got {self.delta_rot_scale_rad}")

    @property
    def uses_images(self) -> bool:
        if self.observation_mode == "auto":
            return bool(self.image_features)
        return self.observation_mode == "pixels"

    @property
    def image_key(self) -> str:
        """The one camera the CNN reads (the first VISUAL feature)."""
        return next(iter(self.image_features))

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(
            lr=self.optimizer_lr,
            betas=self.optimizer_betas,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
        )

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        if STATE_KEY not in self.input_features:
            raise ValueError(f"bcrl needs '{STATE_KEY}' among the input features")
        if self.uses_images and len(self.image_features) != 1:
            raise ValueError(f"bcrl in pixels mode reads exactly one camera, got {list(self.image_features)}")
        if not self.uses_images and ENV_STATE_KEY not in self.input_features:
            raise ValueError(f"bcrl in low_dim mode needs '{ENV_STATE_KEY}' among the input features")
        if self.critic_observation == "privileged":
            if not self.uses_images:
                raise ValueError("critic_observation='privileged' is for pixels policies: a low_dim actor and its"
                                 " critic already read observation.environment_state")
            if ENV_STATE_KEY not in self.input_features:
                raise ValueError(f"critic_observation='privileged' reads '{ENV_STATE_KEY}': the dataset lacks it")
        action = self.action_feature
        if action is not None and tuple(action.shape) != (ACTION_DIM,):
            raise ValueError(f"bcrl predicts the {ACTION_DIM}-D delta action, got action shape {action.shape}")
