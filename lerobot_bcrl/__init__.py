"""lerobot-bcrl: BC+RL (behavioural cloning + PPO) from non-optimal demonstrations, as a LeRobot plugin.

Importing the package registers with LeRobot the env type `bcrl_lift` (and its gymnasium id) and the
policy type `bcrl`, and lets LeRobotDataset decode with `video_backend=bcrl_frame_cache` (frame_cache.py).
"""

from lerobot_bcrl import envs  # noqa: F401  (registers EnvConfig "bcrl_lift" and the gym id)
from lerobot_bcrl.policies import bcrl  # noqa: F401  (registers PreTrainedConfig "bcrl")
from lerobot_bcrl import frame_cache  # noqa: F401  (installs the video backend bcrl_frame_cache)

__version__ = "0.1.0"
