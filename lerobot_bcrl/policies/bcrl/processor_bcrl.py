"""Pre/post-processing pipelines of the `bcrl` policy, and the route that keeps `aux.*` targets in a batch.

Preprocessor: rename -> add batch dim -> device -> normalize (VISUAL/STATE/ENV mean-std, ACTION identity).
Postprocessor: unnormalize (identity for ACTION) -> cpu. Both are LeRobot's default steps; with
`cube_yaw_features` the preprocessor computes `observation.cube_yaw` before it normalizes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from lerobot.configs.types import FeatureType, PipelineFeatureType, PolicyFeature
from lerobot.processor import (
    ObservationProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStepRegistry,
    converters,
    make_default_policy_processor_steps,
    make_policy_processor_pipelines,
)

from lerobot_bcrl import geometry
from lerobot_bcrl.features import (
    AUX_EEF_POS_KEY,
    AUX_GRASP_POS_KEY,
    AUX_GRASP_VALID_KEY,
    AUX_IMITATE_KEY,
    AUX_PROPRIO_ACTION_KEY,
    CUBE_YAW_KEY,
    ENV_STATE_CUBE_QUAT,
    ENV_STATE_KEY,
    STATE_EEF_QUAT,
    STATE_KEY,
    cube_yaw_dim,
)
from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig

AUX_TARGET_KEYS = (AUX_EEF_POS_KEY, AUX_GRASP_POS_KEY, AUX_GRASP_VALID_KEY, AUX_IMITATE_KEY, AUX_PROPRIO_ACTION_KEY)


def keep_aux_targets_in_batches() -> None:
    """Make LeRobot's batch<->transition converters carry `aux.*` as complementary data.

    `batch_to_transition` keeps only `observation.*`, `action`, `*_is_pad` and a fixed tuple of metadata
    keys (`converters._COMPLEMENTARY_KEYS`); everything else is dropped *before* the first processor step
    runs, so no ProcessorStep can rescue the aux targets. A custom `to_transition` would work for a fresh
    pipeline, but `lerobot.policies.factory.make_pre_post_processors` hard-codes `batch_to_transition`
    when it loads a saved pipeline (every `--resume=true`). Extending that tuple is the one route that
    holds for both; `transition_to_batch` puts complementary data back into the batch, and
    `DeviceProcessorStep` moves it to the policy's device. Checked against lerobot 0.6.1 (pinned) by
    tests/test_policy_aux.py. Idempotent.
    """
    missing = tuple(k for k in AUX_TARGET_KEYS if k not in converters._COMPLEMENTARY_KEYS)
    if missing:
        converters._COMPLEMENTARY_KEYS = (*converters._COMPLEMENTARY_KEYS, *missing)


keep_aux_targets_in_batches()


def yaw_of(quat_xyzw: torch.Tensor) -> torch.Tensor:
    """Heading of the body's x axis on the world xy plane (rad), batched; geometry.yaw_of for tensors."""
    x, y, z, w = torch.nn.functional.normalize(quat_xyzw, dim=-1).unbind(-1)
    return torch.atan2(2 * (x * y + z * w), 1 - 2 * (y * y + z * z))


@dataclass
@ProcessorStepRegistry.register(name="bcrl_cube_yaw_features")
class CubeYawFeaturesStep(ObservationProcessorStep):
    """`observation.cube_yaw` = (sin 4d, cos 4d), d the yaw from the fingers to the cube (geometry.cube_yaw_error
    up to whole quarter turns), from the raw quaternions: run it before the normalizer. With `signed`, also
    d / (pi/4) itself, in [-1, 1): the turn to the nearest face, which flips sign at +-45 degrees."""

    signed: bool = False

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        eef_quat = observation[STATE_KEY][..., STATE_EEF_QUAT]
        cube_quat = observation[ENV_STATE_KEY][..., ENV_STATE_CUBE_QUAT]
        d = yaw_of(cube_quat) - yaw_of(eef_quat)
        features = [torch.sin(4 * d), torch.cos(4 * d)]
        if self.signed:
            features.append(geometry.nearest_face_turn(d) / (math.pi / 4))
        observation[CUBE_YAW_KEY] = torch.stack(features, dim=-1)
        return observation

    def get_config(self) -> dict[str, Any]:
        return {"signed": self.signed}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        features[PipelineFeatureType.OBSERVATION][CUBE_YAW_KEY] = PolicyFeature(type=FeatureType.ENV, shape=(cube_yaw_dim(self.signed),))
        return features


def make_bcrl_pre_post_processors(
    config: BCRLConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    steps = make_default_policy_processor_steps(config, dataset_stats)
    yaw = [CubeYawFeaturesStep(signed=config.cube_yaw_signed)] if config.cube_yaw_features else []
    return make_policy_processor_pipelines(
        input_steps=[steps.rename_observations, steps.add_batch_dim, steps.to_device, *yaw, steps.normalize],
        output_steps=[steps.unnormalize, steps.to_cpu],
    )
