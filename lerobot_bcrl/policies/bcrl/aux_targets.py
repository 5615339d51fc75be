"""Keeps the `aux.*` BC targets in a batch through LeRobot's processor pipelines (one patch, one LeRobot version).

`lerobot.processor.converters.batch_to_transition` keeps only `observation.*`, `action`, `*_is_pad` and a fixed
tuple of metadata keys (`converters._COMPLEMENTARY_KEYS`); anything else is dropped before the first processor step
runs, so no ProcessorStep can rescue the aux targets. A custom `to_transition` would serve a fresh pipeline, but
`make_pre_post_processors` hard-codes `batch_to_transition` when it loads a saved one (every `--resume=true`).
Extending that tuple is the one route that holds for both; `transition_to_batch` puts complementary data back
and `DeviceProcessorStep` moves it to the policy's device. tests/test_policy_aux.py checks it end to end.
"""

from __future__ import annotations

import lerobot
from lerobot.processor import converters

from lerobot_bcrl.features import AUX_EEF_POS_KEY, AUX_GRASP_POS_KEY, AUX_GRASP_VALID_KEY, AUX_IMITATE_KEY

LEROBOT_VERSION = "0.6.1"  # the version whose converters this patch was written against
AUX_TARGET_KEYS = (AUX_EEF_POS_KEY, AUX_GRASP_POS_KEY, AUX_GRASP_VALID_KEY, AUX_IMITATE_KEY)


def require_lerobot_version() -> None:
    """Refuse a LeRobot other than the one this package's two patches (here and frame_cache.py) were written for."""
    if lerobot.__version__ != LEROBOT_VERSION or not hasattr(converters, "_COMPLEMENTARY_KEYS"):
        raise RuntimeError(
            f"lerobot_bcrl needs lerobot=={LEROBOT_VERSION} (found {lerobot.__version__}): it extends two private parts"
            " of LeRobot, lerobot.processor.converters._COMPLEMENTARY_KEYS (the bcrl policy's aux.* targets) and"
            " lerobot.datasets.dataset_reader's decode_video_frames and DatasetReader._query_videos (the"
            " bcrl_frame_cache video backend), which other"
            f" versions may not have. Install lerobot=={LEROBOT_VERSION}."
        )


def keep_aux_targets_in_batches() -> None:
    """Add `AUX_TARGET_KEYS` to LeRobot's complementary keys (idempotent); refuse a LeRobot it was not written for."""
    require_lerobot_version()
    missing = tuple(key for key in AUX_TARGET_KEYS if key not in converters._COMPLEMENTARY_KEYS)
    if missing:
        converters._COMPLEMENTARY_KEYS = (*converters._COMPLEMENTARY_KEYS, *missing)
