"""Policies of lerobot-bcrl, each in LeRobot's one-folder-per-policy layout.

Only `bcrl` so far: the one network that serves BC and PPO (method.md section 2).
"""
