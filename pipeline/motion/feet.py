"""Where a G1 reference motion's feet touch the ground, and its flights, from its own kinematics.

Each foot's sole is the set of its collision capsules' end points, placed with the ankle body's pose.
A foot is planted where its lowest sole point stays still for a while; the contact then grows while
that point stays at the same floor height, so a toe-off, a heel strike and a foot on a box all count.
A clip from a video pose estimator jitters: it is smoothed first and read with wider tolerances
(`contacts_from_points`). A flight is a stretch with no foot down (`find_flights`).

This is the one detector of contacts and flights on a reference: the keyframe stage's take-offs and
landings, the retarget's quality report (`jump`), its torque check and the feedforward targets all use
it. (The retarget's own `retarget/contacts.py` decides where to pin the human's feet flat before the
IK: a stance of the whole sole, not a touch of the ground.)
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
MIN_FLIGHT_S = 0.04  # s with no foot down that make a flight (2 frames at 50 fps: a triple jump's 0.1 s
# flights lose a frame at either end to a jittery clip's tolerances)
MIN_SWING_S = 0.05  # a jittery foot off the floor for less than this never left it
APEX_WINDOW_S = 0.1  # a still stretch with the foot lower than it on both sides within this is in the air
# A pose estimator's clip (GVHMR and the like: feet jittering by a centimetre from frame to frame).
JITTER_FIT_S = 0.2  # the jitter is what local quadratic fits over this window leave
NOISE_FLOOR_M = 0.001  # height jitter above this: the clip is smoothed and the tolerances widened
SMOOTHING_S = 0.1  # quadratic Savitzky-Golay fit over this window
STILL_SPEED_PER_JITTER = 2.0  # still speed + this x jitter x fps
HEIGHT_TOL_PER_JITTER = 2.0  # height tolerance + this x jitter


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
    """(T, 2) height of each foot's lowest sole point (capsule surface) and that point's speed."""
    _, radius = _sole_points()
    return lowest_point_height_and_speed(sole_points_world(motion), motion.fps, radius)


def lowest_point_height_and_speed(points: np.ndarray, fps: float, radius: float = 0.0
                                  ) -> tuple[np.ndarray, np.ndarray]:
    """(T, F) height of each foot's lowest point and that point's speed, from (T, F, P, 3) points per foot
    (`radius` below the lowest point is the sole's surface).

    The speed is the smaller of the backward and forward differences: a foot on its last frame on
    the ground (or first one back) is still on one side, which central differences would blur."""
    pts = points
    lowest = np.argmin(pts[..., 2], axis=-1)  # (T, F)
    step = np.diff(pts, axis=0) * fps  # (T-1, F, P, 3)
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


def find_flights(contact: np.ndarray, fps: float, min_flight: float = MIN_FLIGHT_S) -> list[tuple[int, int]]:
    """(take-off, landing) frames of each stretch of at least `min_flight` seconds with no foot in
    contact, inside the clip: the last frame with a foot down before it and the first one after."""
    airborne = ~np.asarray(contact, bool).any(axis=1)
    min_len = max(1, int(round(min_flight * fps)))
    flights = []
    for a, b in runs(airborne):
        if a == 0 or b >= len(airborne) or b - a < min_len:
            continue  # a clip starting or ending in the air has no takeoff/landing there
        flights.append((int(a) - 1, int(b)))
    return flights


def height_jitter(height: np.ndarray, fps: float) -> float:
    """A robust estimate (m) of the jitter of (T, F) foot heights: the median absolute deviation from
    local quadratic fits over JITTER_FIT_S, which a standing foot (0) or a flying one (a parabola) leaves
    near zero and an estimator's noise does not, as a standard deviation. (Second differences would miss
    most of it: a clip estimated at 30 fps and resampled to 50 is piecewise linear between its frames.)"""
    from scipy.signal import savgol_filter

    window = 2 * int(round(0.5 * JITTER_FIT_S * fps)) + 1
    if len(height) <= window:
        return 0.0
    residual = height - savgol_filter(height, window, 2, axis=0)
    return float(np.max(1.4826 * np.median(np.abs(residual), axis=0)))


def detect_foot_contacts(motion: Motion) -> np.ndarray:
    """(T, 2) bool contact of (left, right) foot of a G1 reference (see `contacts_from_points`)."""
    _, radius = _sole_points()
    return contacts_from_points(sole_points_world(motion), motion.fps, radius)


def contacts_from_points(points: np.ndarray, fps: float, radius: float = 0.0) -> np.ndarray:
    """(T, F) bool contact of each foot, from (T, F, P, 3) points on its sole (`radius` above the sole's
    surface). A foot is planted where its lowest point is still for a while on a floor it does not rise
    to and fall from (a foot at the top of a vertical jump is still too); the contact grows from there
    while the point stays at that stretch's floor height (so toe-off and heel strike count, and a step
    onto a box or a sloped floor has its own floor).

    On a jittery clip (a pose estimator's: `height_jitter` above NOISE_FLOOR_M) the points are first
    smoothed over SMOOTHING_S and the speed and height tolerances widened with the jitter; a clean
    reference is read frame by frame."""
    from scipy.signal import savgol_filter

    t, feet = points.shape[:2]
    height, _ = lowest_point_height_and_speed(points, fps, radius)
    jitter = height_jitter(height, fps)
    if jitter > NOISE_FLOOR_M:
        from scipy.ndimage import median_filter

        window = max(5, 2 * int(round(0.5 * SMOOTHING_S * fps)) + 1)
        if t > 2 * window:
            # Heights through a median (it keeps the corner of a touch-down where a fit would round it
            # off early), speeds from a local quadratic fit of the points.
            height = median_filter(height, size=(window, 1), mode="nearest")
            points = savgol_filter(points, window, 2, axis=0)
        # The sole's middle, not its lowest point: which point is lowest flickers with the jitter; along
        # the floor only (up and down the jitter is as large and the height tells). A single frame's
        # speed is mostly noise: the median of its neighbours' is the foot's.
        speed = np.linalg.norm(np.gradient(points.mean(axis=2)[..., :2], 1.0 / fps, axis=0), axis=-1)
        speed = median_filter(speed, size=(window, 1), mode="nearest")
    else:
        jitter = 0.0
        _, speed = lowest_point_height_and_speed(points, fps, radius)
    still_speed = STILL_SPEED + STILL_SPEED_PER_JITTER * jitter * fps
    height_tol = HEIGHT_TOL + HEIGHT_TOL_PER_JITTER * jitter
    min_len = max(2, int(np.ceil(STILL_FRAMES_S * fps)))
    around = max(1, int(round(APEX_WINDOW_S * fps)))
    contact = np.zeros((t, feet), bool)
    for foot in range(feet):
        h, v = height[:, foot], speed[:, foot]
        for a, b in runs(v < still_speed):
            if b - a < min_len:
                continue
            floor = float(np.median(h[a:b]))
            before, after = h[max(0, a - around):a], h[b:b + around]
            if before.size and after.size and before.min() < floor - height_tol and after.min() < floor - height_tol:
                continue  # higher than the frames either side: the top of a flight, not a floor
            near = (np.abs(h - floor) < height_tol) & (v < EXTEND_SPEED)
            lo, hi = a, b
            while lo > 0 and near[lo - 1]:
                lo -= 1
            while hi < t and near[hi]:
                hi += 1
            # A foot coming down slows into its touch-down, and the wide tolerance of a jittery clip
            # lets in the frames before it: a frame well above the next two is not down yet.
            while jitter and hi - lo > 2 and h[lo] - h[lo + 1:lo + 3].min() > 0.5 * height_tol:
                lo += 1
            # A jittery still stretch may span a flight straight up (the foot still along the floor):
            # only its frames at the floor's height are on it.
            contact[lo:hi, foot] = near[lo:hi] if jitter else True
        if jitter:  # a frame or two of jitter out of a stance: no foot swings and lands that fast
            for a, b in runs(~contact[:, foot]):
                if 0 < a and b < t and b - a < MIN_SWING_S * fps:
                    contact[a:b, foot] = True
    return contact
