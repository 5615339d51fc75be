"""Offscreen camera rendering of a MuJoCo model, once per control step, headless (EGL).

Under Mesa's software EGL a frame's cost is the geometry, not the pixels: the Lift scene's visual meshes hold
284,527 triangles, drawn whatever the image size. The "cheap" renderer (the default) draws a copy of the model
whose visual meshes are simplified by vertex clustering on a 1 cm grid (28,519 triangles; at 128x128 a pixel on
the table is about 1 cm) without shadows, reflections, skybox or multisampling; the full renderer draws the
original meshes with all of them. Both draw the visual geoms only (robosuite's group 1), as robosuite's own
renderer does, never the collision geoms. Speed and the two frames side by side: docs/RESULTS.md#env-throughput.
"""

from __future__ import annotations

import copy
import os

os.environ.setdefault("MUJOCO_GL", "egl")
if os.environ["MUJOCO_GL"] == "egl":
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

VISUAL_GEOM_GROUP = 1  # robosuite's visual geoms; group 0 holds the collision geoms
LOW_POLY_CELL_M = 0.01  # vertex clustering grid of the cheap renderer's meshes


def low_poly_copy(model: mujoco.MjModel, cell_m: float = LOW_POLY_CELL_M) -> mujoco.MjModel:
    """A copy of `model` for drawing, its meshes simplified by vertex clustering on a `cell_m` grid.

    The vertices of a grid cell collapse onto the first of them and the triangles that collapse are dropped; each
    kept triangle keeps its corners' normals and texture coordinates. Only what the renderer uploads changes
    (mesh faces), so the copy draws `data` of the original model.
    """
    model = copy.deepcopy(model)
    for mesh in range(model.nmesh):
        vert_adr, n_vert = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        face_adr, n_face = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
        cells = np.floor(model.mesh_vert[vert_adr : vert_adr + n_vert] / cell_m).astype(np.int64)
        _, first_in_cell, cell_of_vertex = np.unique(cells, axis=0, return_index=True, return_inverse=True)
        faces = first_in_cell[cell_of_vertex.ravel()][model.mesh_face[face_adr : face_adr + n_face]]
        keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
        n_kept = int(keep.sum())
        face_slice = slice(face_adr, face_adr + n_face)
        model.mesh_facenormal[face_adr : face_adr + n_kept] = model.mesh_facenormal[face_slice][keep]
        if model.mesh_facetexcoord.size:
            model.mesh_facetexcoord[face_adr : face_adr + n_kept] = model.mesh_facetexcoord[face_slice][keep]
        model.mesh_face[face_adr : face_adr + n_kept] = faces[keep]
        model.mesh_facenum[mesh] = n_kept
    return model


class CameraRenderer:
    """Renders one named camera of `model` to uint8 HWC RGB, cheap (the default) or at full quality."""

    def __init__(self, model: mujoco.MjModel, camera_name: str, height: int, width: int, cheap: bool = True):
        self.camera_name = camera_name
        if cheap:
            model = low_poly_copy(model)
            # Multisample anti-aliasing is done in software under Mesa: it halves the frame rate.
            # The offscreen buffer is sized from the model when the context is made, so set it first.
            model.vis.quality.offsamples = 0
        self._renderer = mujoco.Renderer(model, height=height, width=width)
        if cheap:
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
        self._scene_option = mujoco.MjvOption()
        self._scene_option.geomgroup[:] = 0
        self._scene_option.geomgroup[VISUAL_GEOM_GROUP] = 1

    def render(self, data: mujoco.MjData) -> np.ndarray:
        self._renderer.update_scene(data, camera=self.camera_name, scene_option=self._scene_option)
        return self._renderer.render()

    def close(self) -> None:
        self._renderer.close()
