"""The reference drawn as a translucent second G1 in another model's scene.

The ghost has its own model and data (the G1 alone, no terrain) so the scene being drawn keeps its physics
untouched: its moving geoms are appended to the scene after `update_scene` (`mjv_addGeoms`) and recoloured.
"""

from __future__ import annotations

import mujoco
import numpy as np

GHOST_RGBA = (0.25, 0.55, 1.0, 0.35)


class Ghost:
    def __init__(self, rgba=GHOST_RGBA):
        from pipeline.robot.g1 import build_model

        self.model = build_model(visual=True)
        self.data = mujoco.MjData(self.model)
        self.option = mujoco.MjvOption()
        self.perturb = mujoco.MjvPerturb()
        self.rgba = np.asarray(rgba, dtype=np.float32)
        self.nq = self.model.nq

    def draw(self, scene: mujoco.MjvScene, qpos: np.ndarray, rgba=None) -> int:
        """Adds the G1 posed at `qpos` (the model's layout: root xyz, quat wxyz, joints); returns geoms added."""
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        first = scene.ngeom
        mujoco.mjv_addGeoms(self.model, self.data, self.option, self.perturb, mujoco.mjtCatBit.mjCAT_DYNAMIC, scene)
        color = self.rgba if rgba is None else np.asarray(rgba, dtype=np.float32)
        for i in range(first, scene.ngeom):
            geom = scene.geoms[i]
            geom.rgba[:] = color
            geom.matid = -1  # a material's own colour would win over rgba
            geom.category = mujoco.mjtCatBit.mjCAT_DECOR
        return scene.ngeom - first
