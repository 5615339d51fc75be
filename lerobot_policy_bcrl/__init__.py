"""Plugin shim: LeRobot imports installed distributions named `lerobot_policy_*` at start-up.

Importing this registers the `bcrl` policy config and the `bcrl_lift` env config with LeRobot.
"""

import lerobot_bcrl  # noqa: F401  (registration happens on import)
