"""One offscreen renderer for every picture of the robot: a side camera that follows the pelvis, the styled
scene (render/style.py), the reference as a ghost (render/ghost.py) and a caption (render/caption.py).

Rendering runs headless through the GL that importing `pipeline` chose (`MUJOCO_GL`): EGL where libEGL is
installed (on a machine without a GPU Mesa's llvmpipe serves it: Debian packages libegl1 + libegl-mesa0 +
libgl1-mesa-dri), else OSMesa (libosmesa6). Multisampling stays off (on llvmpipe it costs more than it shows);
the shadow and the sky are on. What a frame costs on 2 cores: benchmarks/render_cost.py. No torch here: the
deployment loop uses it too.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import mujoco
import numpy as np

from pipeline.render.style import mark_raised_terrain

FOG_START_M, FOG_END_M = 6.0, 12.0


@dataclass(frozen=True)
class CameraRig:
    """A side view at a fixed distance, looking at the pelvis's ground position at `height`: the robot stays
    the same size on screen and the floor's checker shows how far it went."""
    distance: float = 3.2
    azimuth: float = 90.0      # looking along +y: a motion along +x crosses the frame left to right
    elevation: float = -8.0
    height: float = 0.7


class Renderer:
    def __init__(self, model: mujoco.MjModel, width: int = 1280, height: int = 720, *,
                 rig: CameraRig = CameraRig(), shadows: bool = True):
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        model.vis.quality.offsamples = 0
        # fog from FOG_START_M to FOG_END_M off the camera (MuJoCo counts in the model's extent, which the
        # terrain's long boxes make tens of metres); the GL context copies it when it is made
        model.vis.map.fogstart = FOG_START_M / model.stat.extent
        model.vis.map.fogend = FOG_END_M / model.stat.extent
        mark_raised_terrain(model)
        try:
            self.renderer = mujoco.Renderer(model, height, width, max_geom=4000)
        except Exception as error:
            raise RuntimeError(
                f"offscreen rendering failed with MUJOCO_GL={os.environ.get('MUJOCO_GL')} ({error}); "
                "install Mesa EGL (libegl1 libegl-mesa0 libgl1-mesa-dri) or set MUJOCO_GL=osmesa "
                "with libosmesa6") from error
        flags = self.renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(shadows)
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        flags[mujoco.mjtRndFlag.mjRND_FOG] = 1
        self.option = mujoco.MjvOption()
        self.option.sitegroup[:] = 0  # tracking sites and foot sites are for the physics, not the picture
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.distance, self.camera.azimuth, self.camera.elevation = rig.distance, rig.azimuth, rig.elevation
        self.rig, self.model, self.width, self.height = rig, model, width, height
        self._ghost = None

    def frame(self, data: mujoco.MjData, *, follow: np.ndarray | None = None, ghosts=(),
              caption: list[str] | None = None, decorate=None) -> np.ndarray:
        """RGB frame (H, W, 3) uint8. `follow`: the world point the camera tracks (default: the root);
        `ghosts`: (qpos, rgba or None) pairs drawn as translucent G1s; `decorate(scene)`: draws more geoms
        into the scene (the retarget preview's person)."""
        point = data.qpos[0:3] if follow is None else np.asarray(follow)
        self.camera.lookat[:] = [point[0], point[1], self.rig.height]
        # the lights follow the robot (mj_camlight): frames posed by mj_kinematics alone would have them unset
        mujoco.mj_comPos(self.model, data)
        mujoco.mj_camlight(self.model, data)
        self.renderer.update_scene(data, camera=self.camera, scene_option=self.option)
        scene = self.renderer.scene
        for qpos, rgba in ghosts:
            if self._ghost is None:
                from pipeline.render.ghost import Ghost

                self._ghost = Ghost()
            self._ghost.draw(scene, qpos, rgba)
        if decorate is not None:
            decorate(scene)
        rgb = self.renderer.render()
        if caption:
            from pipeline.render.caption import draw_caption

            rgb = draw_caption(rgb, caption)
        return rgb

    def close(self) -> None:
        self.renderer.close()

