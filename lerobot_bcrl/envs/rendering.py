"""Offscreen camera rendering of a MuJoCo model, once per control step, headless (EGL).

robosuite's own camera path renders with shadows, reflections and 4x multisampling, through its own
context; we render the same camera with MuJoCo's `Renderer` and can switch those effects off ("cheap"
mode), which is about 3x faster under Mesa's software EGL (docs/RESULTS.md).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
if os.environ["MUJOCO_GL"] == "egl":
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402


class CameraRenderer:
    """Renders one named camera of `model` to uint8 HWC RGB."""

    def __init__(self, model: mujoco.MjModel, camera_name: str, height: int, width: int, cheap: bool = True):
        self.camera_name = camera_name
        if cheap:
            # Multisample anti-aliasing is done in software under Mesa: it halves the frame rate.
            # The offscreen buffer is sized from the model when the context is made, so set it first.
            model.vis.quality.offsamples = 0
        self._renderer = mujoco.Renderer(model, height=height, width=width)
        if cheap:
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0

    def render(self, data: mujoco.MjData) -> np.ndarray:
        self._renderer.update_scene(data, camera=self.camera_name)
        return self._renderer.render()

    def close(self) -> None:
        self._renderer.close()
