"""Quality report of a retargeted motion, and the floor geometry it needs.

Definitions (all on the final 50 Hz motion unless said):
  keypoint_err_mm           mean over source frames and tracked keypoints of |robot - target|,
                            both taken relative to their pelvis; targets are the scaled human
                            keypoints of `skeleton.transfer_skeleton` (the human skeleton with the
                            robot's bone lengths), after ground and contact correction.
  keypoint_err_uniform_mm   the same against the human joints scaled uniformly (s * (p - pelvis)),
                            for reference: it includes the proportion mismatch and cannot be ~0.
  foot_skate_mm_per_frame   mean horizontal motion of an ankle between consecutive output frames
                            while its foot is in contact (max also reported).
  max_penetration_mm        deepest point of any robot collision geom below z = 0.
  joint_limit_violations    number of (frame, joint) entries outside the model's joint range.
  max_joint_vel             largest |joint velocity| in rad/s (central differences at 50 Hz).
  jump                      the flights of the robot's reference, found by the keyframe stage's detector
                            (motion/feet.py: no foot down for at least 0.04 s): how many (flights_found), and
                            for each (flights, in order) its take-off and landing times, the root's distance
                            and peak height, its duration, and the downward acceleration of the robot's centre
                            of mass over it (gravity_m_s2, a least-squares parabola, `flight_gravity`); the
                            longest one's figures also at the top level. Retargeting scales
                            distances, not time, so a clip's flight falls at about scale x 9.81 on the robot
                            (the bundled sample 8.3 at scale 0.77; the shared clips 6.1-9.1): the robot, which
                            falls at 9.81, lands earlier and faster than the reference from the same take-off.
  human_jump_scaled         the same flights (the same moments of the clip) measured on the person's pelvis
                            and centre of mass, scaled by the retargeting's scale: what the retargeting kept of
                            each jump. A person in flight falls at 9.81, so this gravity is scale x 9.81
                            (x 1/scale with `time_scale: froude`) where the person's flight and the
                            reference's coincide: the bundled sample's 7.5 (its G1 centre of mass 8.3: its
                            mass sits elsewhere, the legs swinging under it). The shared real clips read
                            5.7-9.2 (scale 0.73-0.79): estimated clips, and flights the reference's feet
                            start later than the person's (far jump: 0.1 s, its retargeted feet slide on).
  balance                   can the robot stand where the motion stands still? Over the frames with both
                            feet in contact and the whole-body centre of mass moving slowly (horizontal
                            speed < 0.3 m/s, acceleration < 1 m/s^2): how far its ground projection lies
                            inside the support polygon (convex hull of the sole geoms), minimum in mm
                            (negative: outside, the robot would topple tracking it), and how many frames.
                            The same for the zero-moment point of the centre of mass's path
                            (x - z x'' / (g + z''), cart-table model, accelerations from cubic fits over
                            0.2 s) over all double-support frames except the 3 either side of a touch-down
                            or lift-off: where it leaves the feet the motion is dynamically infeasible
                            (zmp_inside_support_min_mm < 0), e.g. a landing that stops the body dead and
                            restarts it; and when (zmp_worst_time_s).
  torque                    can the motors make the motion? The joint torques of its inverse dynamics
                            (robot/dynamics.py: the base carried by the feet on the ground, velocities and
                            accelerations from the same cubic fits over 0.2 s) against each motor's effort
                            limit, over the frames whose fit window holds no touch-down or lift-off:
                            the largest |torque| / limit (above 1 the clip asks a motor for more than it
                            has, e.g. a push-off the person made with stronger ankles), at which joint and
                            when, on how many frames some joint is over its limit, and the peak ratio of
                            each joint that is.
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.signal import savgol_filter
from scipy.spatial import ConvexHull

from pipeline.motion.feet import detect_foot_contacts, find_flights
from pipeline.motion.motion import Motion
from pipeline.robot.dynamics import fit_half_window, joint_torques, smoothed_velocity_and_acceleration
from pipeline.robot.g1 import RobotConfig, joint_limits

SLOW_COM_SPEED = 0.3  # m/s
SLOW_COM_ACCEL = 1.0  # m/s^2
ZMP_SETTLE_FRAMES = 3  # frames either side of a contact change left out of the zero-moment point check
# The zero-moment point's accelerations come from a cubic Savitzky-Golay fit over this window: raw second
# differences of a clip estimated from video are mostly jitter the robot would never follow (several
# metres too far out on the shared clips), and 0.2 s is about the PD-tracked robot's own time scale.
ZMP_SMOOTHING_S = 0.2
GRAVITY = 9.81


def smooth_acceleration(x: np.ndarray, dt: float) -> np.ndarray:
    """Second time derivative of x (T, ...) along axis 0, from local cubic fits over ZMP_SMOOTHING_S."""
    window = 2 * fit_half_window(ZMP_SMOOTHING_S, dt) + 1
    if len(x) < window or window < 5:
        return np.gradient(np.gradient(x, dt, axis=0), dt, axis=0)
    return savgol_filter(x, window, 3, deriv=2, delta=dt, axis=0)


class GeomHeights:
    """Per frame, from collision geoms: the lowest world z of each foot and of the whole robot, and how
    far the centre of mass lies inside the feet."""

    def __init__(self, model: mujoco.MjModel, qpos_index: np.ndarray, foot_bodies: tuple[int, int]):
        self.model = model
        self.data = mujoco.MjData(model)
        self.qpos_index = qpos_index
        self.soles = np.flatnonzero(np.isin(model.geom_bodyid, foot_bodies)
                                    & (model.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE))
        robot_geoms = np.flatnonzero(model.geom_bodyid > 0)
        self.geoms = robot_geoms
        self.foot_of_geom = np.full(len(robot_geoms), -1)
        for side, body in enumerate(foot_bodies):
            self.foot_of_geom[model.geom_bodyid[robot_geoms] == body] = side
        self.types = model.geom_type[robot_geoms]
        self.sizes = model.geom_size[robot_geoms]

    def lowest(self, motion: Motion) -> tuple[np.ndarray, np.ndarray]:
        """(T, 2) lowest foot points, (T,) lowest robot point."""
        t = motion.num_frames
        feet = np.empty((t, 2))
        body = np.empty(t)
        for i in range(t):
            self._pose(motion, i)
            z = self._lowest_z(self.data.geom_xpos[self.geoms], self.data.geom_xmat[self.geoms])
            body[i] = z.min()
            for side in range(2):
                feet[i, side] = z[self.foot_of_geom == side].min()
        return feet, body

    def support_margin(self, motion: Motion) -> dict[str, np.ndarray]:
        """Per frame: the whole-body centre of mass (T, 3), its signed distance (m) inside the convex
        hull of both feet's sole capsules on the ground plane (T,), negative outside, and the same for
        the zero-moment point of the centre of mass's path (T,), x - z x'' / (g + z'')."""
        model, data, soles = self.model, self.data, self.soles
        com = self.center_of_mass(motion)
        hulls = []
        for t in range(motion.num_frames):
            self._pose(motion, t)
            # a capsule's segment ends (along its local z), widened by its radius below
            half = data.geom_xmat[soles].reshape(-1, 3, 3)[:, :2, 2] * model.geom_size[soles, 1:2]
            hulls.append(ConvexHull(np.concatenate([data.geom_xpos[soles, :2] + half, data.geom_xpos[soles, :2] - half])))
        radius = model.geom_size[soles, 0].min()

        def inside(points):
            # facet equations n.x + d <= 0 inside, |n| = 1: the nearest facet gives the distance
            return np.array([radius - (h.equations[:, :2] @ p + h.equations[:, 2]).max() for h, p in zip(hulls, points)])

        acc = smooth_acceleration(com, motion.dt)
        zmp = com[:, :2] - com[:, 2:3] * acc[:, :2] / (GRAVITY + acc[:, 2:3])
        return {"com": com, "inside": inside(com[:, :2]), "zmp_inside": inside(zmp)}

    def center_of_mass(self, motion: Motion) -> np.ndarray:
        """(T, 3) the whole robot's centre of mass per frame."""
        com = np.empty((motion.num_frames, 3))
        for t in range(motion.num_frames):
            self._pose(motion, t)
            mujoco.mj_comPos(self.model, self.data)
            com[t] = self.data.subtree_com[0]
        return com

    def _pose(self, motion: Motion, i: int) -> None:
        """Kinematics of frame i into self.data."""
        self.data.qpos[:3] = motion.root_pos[i]
        self.data.qpos[3:7] = motion.root_quat[i]
        self.data.qpos[self.qpos_index] = motion.joint_pos[i]
        mujoco.mj_kinematics(self.model, self.data)

    def _lowest_z(self, pos: np.ndarray, xmat: np.ndarray) -> np.ndarray:
        zrow = xmat[:, 6:9]  # third row of each rotation: world z of the geom's local axes
        z = pos[:, 2].copy()
        sphere = self.types == mujoco.mjtGeom.mjGEOM_SPHERE
        capsule = self.types == mujoco.mjtGeom.mjGEOM_CAPSULE
        cylinder = self.types == mujoco.mjtGeom.mjGEOM_CYLINDER
        box = self.types == mujoco.mjtGeom.mjGEOM_BOX
        z[sphere] -= self.sizes[sphere, 0]
        z[capsule] -= np.abs(zrow[capsule, 2]) * self.sizes[capsule, 1] + self.sizes[capsule, 0]
        # Cylinder: half-height along its axis plus the radius across it.
        zc = zrow[cylinder, 2]
        z[cylinder] -= np.abs(zc) * self.sizes[cylinder, 1] + np.sqrt(np.clip(1 - zc**2, 0, 1)) * self.sizes[cylinder, 0]
        z[box] -= np.sum(np.abs(zrow[box]) * self.sizes[box, :3], axis=1)
        return z


def flights_report(root_pos: np.ndarray, flights: list[tuple[int, int]], fps: float,
                   com: np.ndarray | None = None) -> dict:
    """quality.json's `jump` (see the module docstring) for the (take-off, landing) frames of each flight:
    the root's horizontal distance from take-off to landing and its peak height above the take-off
    height; with the centre of mass (T, 3), also the gravity its flight obeys."""
    each = []
    for takeoff, landing in flights:
        start, end = root_pos[takeoff], root_pos[landing]
        figures = {"takeoff_s": takeoff / fps, "landing_s": landing / fps,
                   "distance_m": float(np.linalg.norm(end[:2] - start[:2])),
                   "height_m": float(root_pos[takeoff:landing + 1, 2].max() - start[2]),
                   "duration_s": float((landing - takeoff) / fps)}
        if com is not None:
            figures["gravity_m_s2"] = flight_gravity(com[takeoff + 1:landing, 2], fps)
        each.append(figures)
    if each:
        longest = dict(max(each, key=lambda f: f["duration_s"]))
        del longest["takeoff_s"], longest["landing_s"]
    else:
        longest = {"distance_m": 0.0, "height_m": 0.0, "duration_s": 0.0}
        if com is not None:
            longest["gravity_m_s2"] = None
    return {"flights_found": len(each), **longest, "flights": each}


def jump_summary(root_pos: np.ndarray, contacts: np.ndarray, fps: float, com: np.ndarray | None = None) -> dict:
    """`flights_report` of the flights in (T, 2) foot contacts (`motion/feet.py find_flights`)."""
    return flights_report(root_pos, find_flights(contacts, fps), fps, com)


def flight_gravity(com_z: np.ndarray, fps: float) -> float | None:
    """The downward acceleration (m/s², positive) of a flight's centre of mass: twice the leading
    coefficient of a least-squares parabola through its heights. Why it is reported: the retargeting
    scales the clip's distances to the robot, not its timing, so a flight keeps its duration while its
    height shrinks, and falls at about scale × 9.81. The robot falls at 9.81: from the reference's
    take-off it lands earlier, faster and lower than the reference does. None for under 4 frames."""
    if len(com_z) < 4:
        return None
    t = np.arange(len(com_z)) / fps
    return float(-2.0 * np.polyfit(t, com_z, 2)[0])


def foot_skate(ankle_pos: np.ndarray, contacts: np.ndarray) -> tuple[float, float]:
    """Mean and max horizontal ankle motion (m/frame) over consecutive in-contact frames."""
    steps = []
    for side in range(2):
        both = contacts[1:, side] & contacts[:-1, side]
        d = np.linalg.norm(np.diff(ankle_pos[:, side, :2], axis=0), axis=-1)[both]
        steps.append(d)
    d = np.concatenate(steps)
    if d.size == 0:
        return 0.0, 0.0
    return float(d.mean()), float(d.max())


def keypoint_error(robot_pos: np.ndarray, target_pos: np.ndarray, pelvis: int, keypoints: list[int]) -> float:
    r = robot_pos - robot_pos[:, pelvis : pelvis + 1]
    g = target_pos - target_pos[:, pelvis : pelvis + 1]
    return float(np.linalg.norm(r[:, keypoints] - g[:, keypoints], axis=-1).mean())


def joint_report(motion: Motion, model: mujoco.MjModel) -> dict:
    limits = joint_limits(model, motion.joint_names)
    tol = 1e-6
    outside = (motion.joint_pos < limits[:, 0] - tol) | (motion.joint_pos > limits[:, 1] + tol)
    vel = np.abs(motion.joint_vel)
    worst = int(np.argmax(vel.max(axis=0)))
    return {
        "joint_limit_violations": int(outside.sum()),
        "max_joint_vel_rad_s": float(vel.max()),
        "max_joint_vel_joint": motion.joint_names[worst],
    }


def away_from_contact_changes(contacts: np.ndarray, frames: int = ZMP_SETTLE_FRAMES) -> np.ndarray:
    """(T,) bool: frames more than `frames` from a touch-down or lift-off. Impacts happen between two
    frames; accelerations taken from a kinematic reference smear them over their neighbours."""
    keep = np.ones(len(contacts), dtype=bool)
    for c in np.flatnonzero(np.any(np.diff(contacts, axis=0), axis=1)):
        keep[max(c + 1 - frames, 0) : c + 1 + frames] = False
    return keep


def balance_report(motion: Motion, heights: GeomHeights, contacts: np.ndarray) -> dict:
    """See `balance` in the module docstring. contacts: (T, 2) bool, per foot."""
    margin = heights.support_margin(motion)
    com = margin["com"][:, :2]
    vel = np.gradient(com, motion.dt, axis=0)
    acc = np.gradient(vel, motion.dt, axis=0)
    slow = (np.linalg.norm(vel, axis=1) < SLOW_COM_SPEED) & (np.linalg.norm(acc, axis=1) < SLOW_COM_ACCEL)
    both = contacts.all(axis=1)
    checked = slow & both
    inside = margin["inside"][checked]
    # The zero-moment point, over double support away from touch-downs and lift-offs.
    settled = both & away_from_contact_changes(contacts)
    zmp = margin["zmp_inside"]
    worst = int(np.flatnonzero(settled)[np.argmin(zmp[settled])]) if settled.any() else None
    return {"com_inside_support_min_mm": 1e3 * float(inside.min()) if inside.size else None,
            "frames_checked": int(checked.sum()),
            "zmp_inside_support_min_mm": None if worst is None else 1e3 * float(zmp[worst]),
            "zmp_worst_time_s": None if worst is None else worst * motion.dt,
            "zmp_frames_checked": int(settled.sum())}


def torque_report(motion: Motion, model: mujoco.MjModel, robot: RobotConfig) -> dict:
    """See `torque` in the module docstring. The feet that carry the body are the robot's own
    (`motion/feet.py`): the human's contact labels miss the toe-off of a push-off, where the sole rolls
    and moves, and that is where a jump asks the most of the ankles."""
    contacts = detect_foot_contacts(motion)
    qvel, qacc = smoothed_velocity_and_acceleration(motion, ZMP_SMOOTHING_S)
    torques = joint_torques(motion, contacts, robot, model, qvel=qvel, qacc=qacc)
    limit = dict(zip(robot.joint_names, robot.effort_limit))
    ratio = np.abs(torques) / np.array([limit[n] for n in motion.joint_names])
    # Only frames whose smoothing window holds no touch-down or lift-off: a fit across one turns the
    # impact into a torque no motor would be asked for.
    checked = away_from_contact_changes(contacts, fit_half_window(ZMP_SMOOTHING_S, motion.dt))
    if not checked.any():
        return {"peak_effort_ratio": None, "peak_joint": None, "peak_time_s": None, "frames_over_limit": 0,
                "frames_checked": 0, "joints_over_limit": {}}
    ratio = np.where(checked[:, None], ratio, 0.0)
    frame, joint = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
    peaks = ratio.max(axis=0)
    over = {motion.joint_names[j]: float(peaks[j]) for j in np.argsort(-peaks) if peaks[j] > 1.0}
    return {"peak_effort_ratio": float(ratio[frame, joint]),
            "peak_joint": motion.joint_names[joint],
            "peak_time_s": float(frame * motion.dt),
            "frames_over_limit": int((ratio > 1.0).any(axis=1).sum()),
            "frames_checked": int(checked.sum()),
            "joints_over_limit": over}
