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


# ------------------------------------------------------------------------------ hop, step, jump
@dataclass(frozen=True)
class Support:
    """A stretch of the clip during which `feet` stand on the floor at `along` (m from the start,
    the heel's place for a one-footed landing) from `start` to `stop` (s)."""

    feet: tuple[int, ...]  # 0 left, 1 right
    start: float
    stop: float
    along: float


@dataclass(frozen=True)
class EstimatorNoise:
    """What a video pose estimator (GVHMR and the like) does to a clip, as seen on the retargeted G1
    reference: per-frame jitter drawn at the video's rate and interpolated to the reference's (so it is
    correlated over neighbouring frames), feet that slide while they stand, a floor that is not level."""

    jitter_m: float = 0.01  # standard deviation of each foot's position per axis (half of its variance the root's)
    jitter_rad: float = 0.03  # of each foot's pitch
    video_fps: float = 30.0
    slide_m_s: float = 0.15  # a standing foot creeps forward this fast
    slope: float = 0.04  # floor height gained per metre along the travel
    seed: int = 0


CLEAN = EstimatorNoise(jitter_m=0.0, jitter_rad=0.0, slide_m_s=0.0, slope=0.0)

HEEL_STRIKE_RAD = 0.3  # toe up at a touch-down, rolled flat over the first third of the stance
TOE_OFF_RAD = 0.45  # heel up at a lift-off, from the last third of the stance
SWING_LIFT_M = 0.12  # how high a swinging foot rises above the straight line between its supports
SWING_END_SPEED = 0.6  # m/s: at least this fast up from a lift-off and down onto a touch-down
STANCE_DIP_M = 0.07  # the root is this much lower than standing while the legs reach forward and back


def hop_step_jump_supports(flights: tuple[float, float, float] = (0.16, 0.2, 0.24), stance: float = 0.2,
                           speed: float = 2.2, approach_steps: int = 2) -> list[Support]:
    """The supports of a standing start, `approach_steps` walking steps whose contacts abut (one foot
    lands on the frame the other leaves: no flight), then a hop (left to left), a step (left to right)
    and a jump (right to both feet), separated by flights of the given durations (s)."""
    reach = 0.5 * speed * stance  # the root travels this far either side of a standing foot
    step_time, step_length = 0.3, 0.4
    # Both feet stand; the right foot steps first, each step lands as the other foot leaves.
    leaves = [0.8 + step_time, 0.8]  # when each foot leaves the standing start
    supports = [Support((0,), 0.0, leaves[0], 0.0), Support((1,), 0.0, leaves[1], 0.0)]
    t, along, foot = 0.8, 0.0, 1
    for _ in range(2 * approach_steps):  # an even count: the left foot takes the last one, and hops
        along += step_length
        supports.append(Support((foot,), t + step_time, t + 2 * step_time, along))
        t, foot = t + step_time, 1 - foot
    t = supports[-1].stop
    for k, (duration, lands_on) in enumerate(zip(flights, ((0,), (1,), (0, 1)))):
        along += 2 * reach + speed * duration
        start = t + duration
        stop = start + (stance if k < 2 else 0.9)
        supports.append(Support(lands_on, start, stop, along))
        t = stop
    return supports


def _foot_pose(pivot_along: float, lateral: float, pitch: float, floor_slope: float, pivot: str
               ) -> tuple[np.ndarray, float]:
    """Ankle position of a foot pitched by `pitch` (rad, > 0 toe down) about the sole's heel or toe
    end (`pivot`), whose lowest point touches the floor at `pivot_along`."""
    from pipeline.motion.feet import _sole_points

    local, radius = _sole_points()
    end = local[0][np.argmin(local[0][:, 0])] if pivot == "heel" else local[0][np.argmax(local[0][:, 0])]
    end = np.array([end[0], 0.0, end[2]])
    rotated = np.array([np.cos(pitch) * end[0] + np.sin(pitch) * end[2], 0.0,
                        -np.sin(pitch) * end[0] + np.cos(pitch) * end[2]])
    floor = np.array([pivot_along, lateral, floor_slope * pivot_along + radius])
    return floor - rotated, pitch


def _leg_ik(kin, root_pos: np.ndarray, targets_pos: np.ndarray, targets_pitch: np.ndarray,
            joints: np.ndarray) -> tuple[np.ndarray, float]:
    """Leg joints putting both ankle bodies at the target positions (T, 2, 3) with the target pitches
    (T, 2) and no roll or yaw (damped least squares, warm-started); also the largest position error."""
    import mujoco

    model, data = kin.model, kin.data
    sites = [kin.site_index[kin.body_names.index(n)] for n in ("left_ankle", "right_ankle")]
    bodies = model.site_bodyid[sites]
    legs = [kin.qpos_index[:6], kin.qpos_index[6:12]]
    dofs = [np.array([model.jnt_dofadr[model.jnt_qposadr.tolist().index(q)] for q in leg]) for leg in legs]
    worst = 0.0
    jp, jr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    out = joints.copy()
    q = joints[0, :12].copy()
    data.qpos[kin.qpos_index] = joints[0]
    for t in range(len(root_pos)):
        data.qpos[:3], data.qpos[3:7] = root_pos[t], [1.0, 0.0, 0.0, 0.0]
        for _ in range(30):
            data.qpos[kin.qpos_index[:12]] = q
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            done = True
            for side in range(2):
                want = quat.from_axis_angle(np.array([0.0, targets_pitch[t, side], 0.0]))
                err_p = targets_pos[t, side] - data.site_xpos[sites[side]]
                have = data.xquat[bodies[side]]
                err_r = quat.to_axis_angle(quat.multiply(want, quat.conjugate(have)))
                if np.linalg.norm(err_p) > 1e-6 or np.linalg.norm(err_r) > 1e-5:
                    done = False
                mujoco.mj_jacSite(model, data, jp, jr, sites[side])
                jac = np.vstack([jp[:, dofs[side]], jr[:, dofs[side]]])
                step = np.linalg.solve(jac.T @ jac + 1e-6 * np.eye(6), jac.T @ np.concatenate([err_p, err_r]))
                index = slice(6 * side, 6 * side + 6)
                q[index] += step
            if done:
                break
        data.qpos[kin.qpos_index[:12]] = q
        mujoco.mj_kinematics(model, data)
        worst = max(worst, max(float(np.linalg.norm(targets_pos[t, s] - data.site_xpos[sites[s]])) for s in range(2)))
        out[t, :12] = q
    return out, worst


def _ramp(s: np.ndarray) -> np.ndarray:
    """0 -> 1 with zero slope at both ends (smoothstep)."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def synthetic_hop_step_jump(supports: list[Support] | None = None, noise: EstimatorNoise = EstimatorNoise(),
                            fps: float = 50.0, name: str = "hop_step_jump"
                            ) -> tuple[Motion, np.ndarray, list[tuple[int, int]]]:
    """A G1 reference of a hop, step and jump as a pose estimator would hand it over (`noise`), with
    what really happened: (motion, contacts (T, 2) bool of the clean clip, flights as (last frame on
    the ground, first frame back on it)).

    Each foot stands where its supports say (heel strike rolled flat, toe-off rolled onto the toe, the
    lowest point of the sole on the floor), swings in an arc between them; the root stays over the
    supports, dips while the legs reach, and flies a parabola (the retargeted reference's gravity,
    0.77 x 9.81) whenever no foot is down. The legs are solved so the ankles land exactly on their
    targets, jitter included."""
    from scipy.interpolate import PchipInterpolator

    from pipeline.motion.feet import _sole_points

    supports = supports or hop_step_jump_supports()
    kin = RobotKinematics()
    cfg = kin.config
    duration = max(s.stop for s in supports)
    t = np.arange(int(round(duration * fps)) + 1) / fps
    n = len(t)
    local, radius = _sole_points()
    sole_length = float(local[0][:, 0].max() - local[0][:, 0].min())
    slope_pitch = -float(np.arctan(noise.slope))
    rng = np.random.default_rng(noise.seed)

    def video_noise(shape, scale):
        coarse_t = np.arange(int(np.ceil(duration * noise.video_fps)) + 2) / noise.video_fps
        coarse = rng.normal(0.0, scale, (len(coarse_t), *shape)) if scale > 0 else np.zeros((len(coarse_t), *shape))
        flat = coarse.reshape(len(coarse_t), -1)
        return np.stack([np.interp(t, coarse_t, flat[:, i]) for i in range(flat.shape[1])], 1).reshape(n, *shape)

    contacts = np.zeros((n, 2), bool)
    ankle = np.zeros((n, 2, 3))
    pitch = np.zeros((n, 2))
    lateral = (0.119, -0.119)
    for foot in range(2):
        own = [s for s in supports if foot in s.feet]
        ends = []  # per support: (ankle, pitch) at its start and at its end
        for k, s in enumerate(own):
            stride = s.stop - s.start
            lands, leaves = k > 0, k < len(own) - 1
            roll = min(stride / 3.0, 0.1)
            inside = (t >= s.start - 1e-9) & (t <= s.stop + 1e-9)
            contacts[inside, foot] = True
            heel = s.along + noise.slide_m_s * (t - s.start)
            strike = -HEEL_STRIKE_RAD * (1.0 - _ramp((t - s.start) / roll)) if lands else 0.0 * t
            off = TOE_OFF_RAD * _ramp((t - (s.stop - roll)) / roll) if leaves else 0.0 * t
            for i in np.flatnonzero(inside):
                if strike[i] < 0:
                    ankle[i, foot], pitch[i, foot] = _foot_pose(heel[i], lateral[foot], slope_pitch + strike[i],
                                                                noise.slope, "heel")
                else:
                    ankle[i, foot], pitch[i, foot] = _foot_pose(heel[i] + sole_length, lateral[foot],
                                                                slope_pitch + off[i], noise.slope, "toe")
            first, last = np.flatnonzero(inside)[[0, -1]]
            ends.append(((ankle[first, foot].copy(), pitch[first, foot]), (ankle[last, foot].copy(), pitch[last, foot])))
        for k in range(len(own) - 1):  # swing from the end of one support to the start of the next
            (a0, p0), (a1, p1) = ends[k][1], ends[k + 1][0]
            t0, t1 = own[k].stop, own[k + 1].start
            inside = (t > t0 + 1e-9) & (t < t1 - 1e-9)
            s = (t[inside] - t0) / (t1 - t0)
            ankle[inside, foot] = a0 + _ramp(s)[:, None] * (a1 - a0)
            lift = max(SWING_LIFT_M, SWING_END_SPEED * (t1 - t0) / np.pi)  # a long swing comes down as fast
            ankle[inside, foot, 2] = a0[2] + s * (a1[2] - a0[2]) + lift * np.sin(np.pi * s)
            pitch[inside, foot] = p0 + s * (p1 - p0)

    # The root: over the middle of each support, lower while one leg stands alone; a parabola in flight.
    probe = kin.motion(fps, np.array([[0, 0, cfg.default_root_height]] * 2), np.array([[1.0, 0, 0, 0]] * 2),
                       np.tile(cfg.default_joint_pos, (2, 1)))
    from pipeline.motion.feet import foot_height_and_speed

    stand_z = cfg.default_root_height - foot_height_and_speed(probe)[0][0].min()
    knots: dict[float, list[tuple[float, float]]] = {}
    for s in supports:
        # the middle of a stance; 0.2 s into a long one that starts with a landing (the body comes to rest)
        mid = round(s.start + 0.2 if s.start > 0 and s.stop - s.start > 0.5 else 0.5 * (s.start + s.stop), 6)
        both = contacts[int(round(mid * fps))].all()
        knots.setdefault(mid, []).append((s.along + 0.5 * sole_length, 0.0 if both else STANCE_DIP_M))
    knots_t = np.array([0.0, *sorted(knots), duration])
    values = np.array([np.mean(knots[k], axis=0) for k in sorted(knots)])
    values = np.vstack([values[:1] * [1.0, 0.0], values, values[-1:] * [1.0, 0.0]])
    along = PchipInterpolator(knots_t, values[:, 0])(t)
    dip = PchipInterpolator(knots_t, values[:, 1])(t)
    height = stand_z + noise.slope * along - dip
    airborne = ~contacts.any(axis=1)
    from pipeline.motion.feet import runs

    for a, b in runs(airborne):
        span = (b - a + 1) / fps
        s = (np.arange(a, b) - (a - 1)) / fps
        height[a:b] += 0.5 * 0.77 * GRAVITY * s * (span - s)
        dip_ends = np.interp(np.arange(a, b), [a - 1, b], dip[[a - 1, b]])
        height[a:b] += dip[a:b] - dip_ends  # keep the flight's own arc, not the dip schedule's
    root = np.column_stack([along, np.zeros(n), height])

    common = video_noise((3,), noise.jitter_m / np.sqrt(2.0))  # the whole body's, and each foot's own
    root_noisy = root + common
    ankle_noisy = ankle + common[:, None] + video_noise((2, 3), noise.jitter_m / np.sqrt(2.0))
    pitch_noisy = pitch + video_noise((2,), noise.jitter_rad)
    joints = np.tile(cfg.default_joint_pos, (n, 1))
    joints, worst = _leg_ik(kin, root_noisy, ankle_noisy, pitch_noisy, joints)
    if worst > 2e-3:
        raise ValueError(f"the legs cannot reach the supports (ankle {1e3 * worst:.1f} mm off): "
                         "shorter strides or a longer stance")
    root_quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    motion = kin.motion(fps, root_noisy, root_quat, joints, name=name)
    flights = [(a - 1, b) for a, b in runs(airborne) if a > 0 and b < n]
    return motion, contacts, flights
