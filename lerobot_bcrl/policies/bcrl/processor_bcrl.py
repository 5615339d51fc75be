"""Pre/post-processing pipelines of the `bcrl` policy: LeRobot's default steps.

Preprocessor: rename -> add batch dim -> device -> normalize (VISUAL/STATE/ENV mean-std, ACTION identity).
Postprocessor: unnormalize (identity for ACTION) -> cpu. `aux.*` targets pass through (aux_targets.py).
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import (
    PolicyAction,
    PolicyProcessorPipeline,
    make_default_policy_processor_steps,
    make_policy_processor_pipelines,
)

from lerobot_bcrl.policies.bcrl.aux_targets import keep_aux_targets_in_batches
from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig

keep_aux_targets_in_batches()


def make_bcrl_pre_post_processors(
    config: BCRLConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    steps = make_default_policy_processor_steps(config, dataset_stats)
    return make_policy_processor_pipelines(
        input_steps=[steps.rename_observations, steps.add_batch_dim, steps.to_device, steps.normalize],
        output_steps=[steps.unnormalize, steps.to_cpu],
    )
