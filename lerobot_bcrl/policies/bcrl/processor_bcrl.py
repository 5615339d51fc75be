"""Pre/post-processing pipelines of the `bcrl` policy, and the route that keeps `aux.*` targets in a batch.

Preprocessor: rename -> add batch dim -> device -> normalize (VISUAL/STATE/ENV mean-std, ACTION identity).
Postprocessor: unnormalize (identity for ACTION) -> cpu. Both are LeRobot's default steps.
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, converters, make_default_pre_post_processors

from lerobot_bcrl.features import (
    AUX_EEF_POS_KEY,
    AUX_GRASP_POS_KEY,
    AUX_GRASP_VALID_KEY,
    AUX_IMITATE_KEY,
    AUX_PROPRIO_ACTION_KEY,
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


def make_bcrl_pre_post_processors(
    config: BCRLConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    return make_default_pre_post_processors(config, dataset_stats)
