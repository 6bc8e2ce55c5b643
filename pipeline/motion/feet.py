"""Where a G1 reference motion's feet touch the ground, from its own kinematics.

Each foot's sole is the set of its collision capsules' end points, placed with the ankle body's pose.
A foot is planted where its lowest sole point stays still for a while; the contact then grows while
that point stays at the same floor height, so a toe-off, a heel strike and a foot on a box all count.
The keyframe stage finds take-offs and landings with it, the feedforward targets and the retarget's
torque check decide which feet carry the body with it.
"""

from __future__ import annotations

from functools import lru_cache

import mujoco
import numpy as np

from pipeline.common import quat
from pipeline.motion.motion import Motion

STILL_SPEED = 0.25  # m/s: a sole point slower than this may be planted
STILL_FRAMES_S = 0.05  # a planted stretch lasts at least this long (s)
EXTEND_SPEED = 3.0  # m/s: while extending a contact (toe-off, heel strike, a retargeted foot sliding) it may move faster
HEIGHT_TOL = 0.01  # m: contact while the sole stays this close to the stretch's floor height


@lru_cache(maxsize=1)
def _sole_points() -> tuple[np.ndarray, float]:
    """(P, 3) capsule end points of one foot's collision geoms in the ankle-roll body frame, and the
    capsule radius. Left and right feet are mirror images with the same points up to y's sign; both
    are read from the model to stay exact."""
    from pipeline.robot.g1 import build_model

    model = build_model(visual=False)
    out = {}
    radius = 0.0
    for side in ("left", "right"):
        body = model.body(f"{side}_ankle_roll_link").id
        pts = []
        for g in range(model.ngeom):
            if model.geom_bodyid[g] != body or model.geom_type[g] != mujoco.mjtGeom.mjGEOM_CAPSULE:
                continue
            axis = quat.rotate(model.geom_quat[g], np.array([0.0, 0.0, model.geom_size[g][1]]))
            pts += [model.geom_pos[g] + axis, model.geom_pos[g] - axis]
            radius = max(radius, float(model.geom_size[g][0]))
        out[side] = np.array(pts)
    return np.stack([out["left"], out["right"]]), radius


def sole_points_world(motion: Motion) -> np.ndarray:
    """(T, 2, P, 3) the feet's sole points (capsule ends) in the world, from the ankle bodies."""
    local, _ = _sole_points()
    ankles = [motion.body_index("left_ankle"), motion.body_index("right_ankle")]
    pos = motion.body_pos[:, ankles]  # (T, 2, 3)
    rot = motion.body_quat[:, ankles]  # (T, 2, 4)
    world = quat.rotate(rot[:, :, None, :], local[None]) + pos[:, :, None, :]
    return world


def foot_height_and_speed(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2) height of each foot's lowest sole point (capsule surface) and that point's speed.

    The speed is the smaller of the backward and forward differences: a foot on its last frame on
    the ground (or first one back) is still on one side, which central differences would blur."""
    pts = sole_points_world(motion)
    _, radius = _sole_points()
    lowest = np.argmin(pts[..., 2], axis=-1)  # (T, 2)
    step = np.diff(pts, axis=0) / motion.dt  # (T-1, 2, P, 3)
    backward = np.concatenate([step[:1], step], axis=0)
    forward = np.concatenate([step, step[-1:]], axis=0)
    vel = np.where(np.linalg.norm(backward, axis=-1, keepdims=True) < np.linalg.norm(forward, axis=-1, keepdims=True),
                   backward, forward)
    take = lowest[..., None, None]
    height = np.take_along_axis(pts[..., 2], lowest[..., None], axis=-1)[..., 0] - radius
    speed = np.linalg.norm(np.take_along_axis(vel, np.broadcast_to(take, lowest.shape + (1, 3)), axis=2)[:, :, 0],
                           axis=-1)
    return height, speed


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    padded = np.concatenate([[False], mask, [False]]).astype(int)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[0::2], edges[1::2]))


def detect_foot_contacts(motion: Motion) -> np.ndarray:
    """(T, 2) bool contact of (left, right) foot. A foot is planted where its lowest sole point is
    still for a while; the contact grows from there while the sole stays at that stretch's floor
    height (so toe-off and heel strike count, and a step onto a box has its own floor)."""
    height, speed = foot_height_and_speed(motion)
    t = motion.num_frames
    min_len = max(2, int(np.ceil(STILL_FRAMES_S * motion.fps)))
    contact = np.zeros((t, 2), bool)
    for foot in range(2):
        h, v = height[:, foot], speed[:, foot]
        for a, b in runs(v < STILL_SPEED):
            if b - a < min_len:
                continue
            floor = float(np.median(h[a:b]))
            near = (np.abs(h - floor) < HEIGHT_TOL) & (v < EXTEND_SPEED)
            lo, hi = a, b
            while lo > 0 and near[lo - 1]:
                lo -= 1
            while hi < t and near[hi]:
                hi += 1
            contact[lo:hi, foot] = True
    return contact
