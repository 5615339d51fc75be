"""docs/img/render_full_vs_cheap.png: the agentview camera at full quality beside the cheap renderer the
policy sees by default, at the policy's 128x128, with the scripted expert's fingers at the cube.
    MUJOCO_GL=egl .venv/bin/python scripts/render_comparison.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from dataset_tools.experts import ScriptedLiftExpert
from lerobot_bcrl.envs import controller
from lerobot_bcrl.envs.lift import LiftEnv
from lerobot_bcrl.envs.rendering import CameraRenderer

OUT = Path(__file__).resolve().parents[1] / "docs" / "img" / "render_full_vs_cheap.png"
STEPS = 45  # the expert has descended to the cube by then
SIZE = 128
UPSCALE = 3  # nearest-neighbour, so that the pixels stay visible


def main() -> None:
    env = LiftEnv(obs_type="agent_pos")
    observation, _ = env.reset(seed=0)
    expert = ScriptedLiftExpert()
    expert.reset()
    for _ in range(STEPS):
        action, _ = controller.controller_to_delta_action(expert.act(observation))
        observation, *_ = env.step(action)
    frames = []
    for cheap in (False, True):
        renderer = CameraRenderer(env.sim_env.sim.model._model, "agentview", SIZE, SIZE, cheap=cheap)
        frames.append(renderer.render(env.sim_env.sim.data._data))
        renderer.close()
    env.close()
    gap = np.full((SIZE, 4, 3), 255, np.uint8)
    image = Image.fromarray(np.concatenate([frames[0], gap, frames[1]], axis=1))
    image = image.resize((image.width * UPSCALE, image.height * UPSCALE), Image.NEAREST)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    image.save(OUT)
    print(OUT)


if __name__ == "__main__":
    main()
