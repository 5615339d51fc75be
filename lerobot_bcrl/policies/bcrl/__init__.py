"""The `bcrl` policy: CNN + spatial softmax keypoints, an MLP trunk and BC/PPO heads.

Importing this registers the config (`--policy.type=bcrl`) and keeps `aux.*` targets in LeRobot batches.
"""

from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
from lerobot_bcrl.policies.bcrl.processor_bcrl import make_bcrl_pre_post_processors

__all__ = ["BCRLConfig", "make_bcrl_pre_post_processors"]
