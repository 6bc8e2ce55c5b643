"""A virtual gantry for `sim-bridge`: the G1 starts hanging with its feet off the ground, as a real one
hangs from its gantry (Unitree's own MuJoCo simulator has an elastic band for this), is lowered onto
its feet and let go.

The band is a spring-damper from the pelvis to an anchor above the stance, plus a rotational one that
keeps the pelvis upright. The anchor holds `lift_m` above the stance, comes down over the last
`lower_s` seconds before `release_s`, and then the band lets go: by then `adamimic deploy`'s damping
and ramp (1 s + 3 s by default) have put the joints in the default pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np


@dataclass(frozen=True)
class Gantry:
    release_s: float = 4.0  # deploy's damping_s + ramp_s
    lower_s: float = 2.0
    lift_m: float = 0.08
    stiffness: float = 3000.0  # N/m
    damping: float = 400.0  # N·s/m
    rot_stiffness: float = 400.0  # N·m/rad
    rot_damping: float = 40.0  # N·m·s/rad

    def anchor_height(self, stance_z: float, t: float) -> float:
        lowering = min(max((t - (self.release_s - self.lower_s)) / max(self.lower_s, 1e-9), 0.0), 1.0)
        return stance_z + self.lift_m * (1.0 - lowering)

    def apply(self, model: mujoco.MjModel, data: mujoco.MjData, body: int, anchor_xy, stance_z: float, t: float) -> None:
        """Writes the band's force and torque on `body` for time `t` (zero once released)."""
        if t >= self.release_s:
            data.xfrc_applied[body] = 0.0
            return
        anchor = np.array([anchor_xy[0], anchor_xy[1], self.anchor_height(stance_z, t)])
        force = self.stiffness * (anchor - data.xpos[body]) - self.damping * data.qvel[0:3]
        up = data.xmat[body].reshape(3, 3)[:, 2]  # the pelvis's z axis in the world
        omega = data.xmat[body].reshape(3, 3) @ data.qvel[3:6]  # free joint: body-frame angular velocity
        torque = self.rot_stiffness * np.cross(up, [0.0, 0.0, 1.0]) - self.rot_damping * omega
        data.xfrc_applied[body] = np.concatenate([force, torque])
