"""The robosuite Lift env (gymnasium) and its LeRobot EnvConfig `bcrl_lift`."""

from lerobot_bcrl.envs import quiet_robosuite  # noqa: F401  (before any module of ours imports robosuite)
from lerobot_bcrl.envs.configuration_lift import ENV_TYPE, GYM_ID, LiftEnvConfig

__all__ = ["ENV_TYPE", "GYM_ID", "LiftEnvConfig"]
