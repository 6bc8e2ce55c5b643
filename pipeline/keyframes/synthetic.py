"""Synthetic G1 jump motions with known contacts, for tests and demos (no retargeting needed).

The robot stands in its default pose with the soles on the floor; each flight moves the root along a
ballistic arc (gravity 9.81) from one floor level to the next; the feet are planted exactly when the
root is still. An optional arm swing puts a wrist-speed peak at a known time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.common import quat
from pipeline.motion.motion import Motion, RobotKinematics

GRAVITY = 9.81


@dataclass(frozen=True)
class Flight:
    takeoff: float  # s, on the frame grid
    duration: float  # s
    dx: float = 0.0  # m forward (along `heading`)
    dz: float = 0.0  # m floor change (step up > 0)


def synthetic_jump_motion(flights: list[Flight], duration: float, fps: float = 50.0, heading: float = 0.0,
                          hit_time: float | None = None, name: str = "synthetic") -> Motion:
    kin = RobotKinematics()
    cfg = kin.config
    t = np.arange(int(round(duration * fps)) + 1) / fps
    joints = np.tile(cfg.default_joint_pos, (len(t), 1))
    if hit_time is not None:  # right shoulder pitch swings forward, fastest at hit_time
        j = list(kin.joint_names).index("right_shoulder_pitch_joint")
        joints[:, j] += -1.2 * 0.5 * (1.0 + np.tanh((t - hit_time) / 0.06))
    # Root height with the soles touching z = 0 in the default pose.
    from pipeline.motion.feet import foot_height_and_speed

    probe = kin.motion(fps, np.array([[0, 0, cfg.default_root_height]] * 2), np.array([[1.0, 0, 0, 0]] * 2),
                       joints[:2])
    stand_z = cfg.default_root_height - foot_height_and_speed(probe)[0][0].min()

    along = np.zeros(len(t))
    height = np.full(len(t), stand_z)
    base_x, base_z = 0.0, stand_z
    for f in flights:
        s = t - f.takeoff
        v0 = (f.dz + 0.5 * GRAVITY * f.duration**2) / f.duration
        inside = (s > 0) & (s < f.duration)
        after = s >= f.duration
        along[inside] = base_x + f.dx * s[inside] / f.duration
        height[inside] = base_z + v0 * s[inside] - 0.5 * GRAVITY * s[inside] ** 2
        base_x, base_z = base_x + f.dx, base_z + f.dz
        along[after] = base_x
        height[after] = base_z
    direction = np.array([np.cos(heading), np.sin(heading)])
    root_pos = np.column_stack([along * direction[0], along * direction[1], height])
    root_quat = np.tile(quat.from_yaw(np.array(heading)), (len(t), 1))
    return kin.motion(fps, root_pos, root_quat, joints, name=name)


def true_flight_frames(flights: list[Flight], fps: float) -> list[tuple[int, int]]:
    """(last frame on the ground, first frame back on it) of each flight."""
    return [(int(np.floor(f.takeoff * fps + 1e-9)), int(np.ceil((f.takeoff + f.duration) * fps - 1e-9)))
            for f in flights]
