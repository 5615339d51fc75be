"""The Lift env as a LeRobot `EnvConfig` (`--env.type=bcrl_lift`) and its gymnasium registration."""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_bcrl.features import CAMERA_NAME, ENV_STATE_DIM, IMAGE_KEY, STATE_DIM
from lerobot_bcrl.geometry import ACTION_DIM

ENV_TYPE = "bcrl_lift"
GYM_ID = f"gym_{ENV_TYPE}/Lift-v0"

if GYM_ID not in gym.registry:
    gym.register(id=GYM_ID, entry_point="lerobot_bcrl.envs.lift:LiftEnv")


@EnvConfig.register_subclass(ENV_TYPE)
@dataclass
class LiftEnvConfig(EnvConfig):
    task: str | None = "Lift-v0"
    fps: int = 20  # control frequency; also the rate datasets are recorded at
    episode_length: int = 200  # the paper's horizon
    obs_type: str = "pixels_agent_pos"  # or "agent_pos" (low-dim: agent_pos + environment_state)
    image_size: int = 128  # square agentview camera, pixels
    cheap_render: bool = True  # simplified meshes, no shadows/reflections/skybox (docs/environment.md)
    dense_reward: bool = False  # robosuite's shaped reward instead of the paper's sparse 2.25/lifted step
    terminate_on_success: bool = False  # the paper keeps going: return counts lifted steps
    render_mode: str = "rgb_array"
    render_size: int = 128  # size of frames from render() (lerobot-eval videos)
    rerun_dir: str | None = None  # write one rerun .rrd per episode here (with our policy's predictions)
    # "fast": robosuite's controller computed without its per-substep Python, the same trajectories within 1e-8
    # (docs/environment.md); "robosuite": robosuite's own env.step, the reference
    sim_step: str = "fast"
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(ENV_STATE_DIM,)),
        }
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "environment_state": OBS_ENV_STATE,
            f"pixels/{CAMERA_NAME}": IMAGE_KEY,
        }
    )

    def __post_init__(self):
        if self.obs_type == "pixels_agent_pos":
            self.features[f"pixels/{CAMERA_NAME}"] = PolicyFeature(
                type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3)
            )
        elif self.obs_type != "agent_pos":
            raise ValueError(f"obs_type must be 'pixels_agent_pos' or 'agent_pos', got {self.obs_type!r}")

    @property
    def gym_kwargs(self) -> dict:
        return {
            "obs_type": self.obs_type,
            "image_size": self.image_size,
            "cheap_render": self.cheap_render,
            "horizon": self.episode_length,
            "control_freq": self.fps,
            "dense_reward": self.dense_reward,
            "terminate_on_success": self.terminate_on_success,
            "render_mode": self.render_mode,
            "render_size": self.render_size,
            "rerun_dir": self.rerun_dir,
            "sim_step": self.sim_step,
            "max_episode_steps": self.episode_length,
        }
