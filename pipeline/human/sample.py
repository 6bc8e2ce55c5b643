"""The bundled sample input: a SYNTHETIC standing far jump, authored here from keyframe poses.

It is not motion capture and not anyone's recording: it exists so `dvc repro` runs on a fresh
clone without the paper's data. `python -m pipeline.human.sample [OUT.npz]` rewrites
`data/sample/far_jump_synthetic.npz` (AMASS-style SMPL parameters, z-up, 30 fps, deterministic).

How it is made:
  * joint rotations: a handful of scalar pose parameters (pelvis pitch, hip/knee/ankle flexion,
    spine lean, arm swing, elbow bend) keyed at stand, crouch, rise, take-off, tuck, touch-down,
    absorb and recover, interpolated with monotone cubics (no overshoot), turned into SMPL
    local axis-angles of a body whose two sides move alike;
  * until the bottom of the crouch the feet are pinned (their mean x stays put, the lowest sole point
    stays on the floor z = 0), so the body moves by the pose alone;
  * in the push-off the centre of mass is planned (`planned_push`): it rises to the take-off height
    and speed and moves forward as an inverted pendulum about one zero-moment point between the ankles
    and the balls of the feet, chosen so that it leaves the ground at the speed the flight and landing
    need; the legs are solved so the feet stay flat where they stood. The arms swing up through the
    take-off and stop in the air, where stopping them asks nothing of the ankles;
  * in the air the whole-body centre of mass (`smpl.center_of_mass`) follows a true projectile,
    x(t) = x0 + vx t, z(t) = z0 + vz t - g t^2 / 2 with g = 9.81 m/s^2, and the whole body leans so
    that its angular momentum about that centre stays what it was at take-off while the arms and legs
    swing (`_spin_free_flight`);
  * after touch-down the centre of mass is planned so the landing can be done without tipping: its
    zero-moment point stays over the landed feet (`balanced_landing`), which fixes how far behind
    the feet it touches down for the flight's speed; the legs are then solved so both feet stay
    flat where they landed, `JUMP_DISTANCE_M` ahead of where they took off.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicHermiteSpline, PchipInterpolator

from pipeline import REPO_ROOT
from pipeline.common import quat
from pipeline.human import smpl
from pipeline.human.sample_dynamics import GRAVITY, balanced_landing, planned_push

SAMPLE_PATH = REPO_ROOT / "data" / "sample" / "far_jump_synthetic.npz"
FPS = 30.0
DURATION_S = 2.9
TAKEOFF_S = 1.2
# The take-off's centre of mass this far below the keyed take-off pose's, which stands on its toes: the planned
# push keeps the feet flat, and the legs must still reach them.
TAKEOFF_CROUCH_M = 0.08
TOUCHDOWN_S = 49.0 / 30.0  # a frame's time: the touch-down key is where the landing's legs are solved
JUMP_DISTANCE_M = 1.0
SOFT_KNEES_M = 0.01
TOUCHDOWN_DROP_M = 0.10  # centre of mass below standing height at touch-down
ABSORB_DEPTH_M = 0.30  # how far the centre of mass sinks below standing height while absorbing the landing

# Pose parameters (radians), SMPL body frame (x left, y up, z front): + about x leans the trunk
# forward / bends the knee / swings the arm back; hip flexion (thigh forward) is negative.
# The crouch, the rise and the absorb bend the knees past the hips (shins tilted forward) so that,
# on the G1, the centre of mass stays over the middle of the feet rather than at the heels, where a
# tracking policy falls over backwards (tests/test_retarget.py::test_bundled_sample_balances_on_the_g1).
PARAMS = ("pelvis_pitch", "spine_lean", "hip_flex", "knee_flex", "ankle_flex", "arm_swing", "elbow_flex")
KEYFRAMES: list[tuple[float, dict[str, float]]] = [
    (0.00, dict(pelvis_pitch=0.00, spine_lean=0.00, hip_flex=0.00, knee_flex=0.00, ankle_flex=0.00, arm_swing=0.0, elbow_flex=0.1)),  # stand ...
    (0.30, dict(pelvis_pitch=0.00, spine_lean=0.00, hip_flex=0.00, knee_flex=0.00, ankle_flex=0.00, arm_swing=0.0, elbow_flex=0.1)),  # ... still
    (0.85, dict(pelvis_pitch=0.55, spine_lean=0.25, hip_flex=-1.05, knee_flex=1.65, ankle_flex=-0.75, arm_swing=1.0, elbow_flex=0.2)),  # crouch, arms back
    (1.03, dict(pelvis_pitch=0.75, spine_lean=0.25, hip_flex=-0.75, knee_flex=1.25, ankle_flex=-0.50, arm_swing=0.2, elbow_flex=0.2)),  # rise, leaning into the jump
    (TAKEOFF_S, dict(pelvis_pitch=0.45, spine_lean=0.10, hip_flex=0.20, knee_flex=0.05, ankle_flex=0.55, arm_swing=-1.3, elbow_flex=0.2)),  # take-off: extended, arms up
    (1.40, dict(pelvis_pitch=0.30, spine_lean=0.15, hip_flex=-1.40, knee_flex=1.50, ankle_flex=0.10, arm_swing=-1.9, elbow_flex=0.4)),  # tuck
    # From the touch-down on, the legs are solved (feet pinned, see make_sample_clip): the leg values
    # of these keys only shape the flight's swing into the touch-down.
    (TOUCHDOWN_S, dict(pelvis_pitch=0.35, spine_lean=0.25, hip_flex=-0.60, knee_flex=0.45, ankle_flex=-0.10, arm_swing=-0.6, elbow_flex=0.3)),  # touch-down: legs reach
    (2.00, dict(pelvis_pitch=0.60, spine_lean=0.30, hip_flex=-1.30, knee_flex=1.85, ankle_flex=-0.80, arm_swing=-0.9, elbow_flex=0.3)),  # absorb
    (2.60, dict(pelvis_pitch=0.00, spine_lean=0.00, hip_flex=0.00, knee_flex=0.00, ankle_flex=0.00, arm_swing=0.0, elbow_flex=0.1)),  # recover
    (2.90, dict(pelvis_pitch=0.00, spine_lean=0.00, hip_flex=0.00, knee_flex=0.00, ankle_flex=0.00, arm_swing=0.0, elbow_flex=0.1)),  # stand
]
CROUCH_KEY, TAKEOFF_KEY, TOUCHDOWN_KEY = 2, 4, 6
LEG_PARAMS = ("hip_flex", "knee_flex", "ankle_flex")
SIDES = ("left", "right")
# The body frame's front (+z) to world +x, its up (+y) to world +z, its left (+x) to world +y.
BODY_TO_WORLD = quat.from_matrix(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
J = {name: i for i, name in enumerate(smpl.SMPL_JOINT_NAMES)}


@dataclass(frozen=True)
class SampleClip:
    poses: np.ndarray  # (T, 66)
    trans: np.ndarray  # (T, 3)
    fps: float
    takeoff_frame: int
    touchdown_frame: int


def _pose_tracks(times: np.ndarray, solved_legs: dict[int, dict] | None = None) -> dict[str, np.ndarray]:
    """The keyed pose parameters at `times`, the legs' per side ("left_hip_flex", ...): the rest
    template is not quite symmetric, so pinning both feet needs slightly different angles.
    `solved_legs` {key index: {side: (hip, knee flexion)}} replaces those keys' legs (flat feet)."""
    key_t = np.array([t for t, _ in KEYFRAMES])
    tracks = {p: PchipInterpolator(key_t, [k[p] for _, k in KEYFRAMES])(times) for p in PARAMS if p not in LEG_PARAMS}
    for side in SIDES:
        keys = [dict(k) for _, k in KEYFRAMES]
        for key, legs in (solved_legs or {}).items():
            hip, knee = legs[side]
            keys[key].update(hip_flex=hip, knee_flex=knee, ankle_flex=_flat_foot_ankle(hip, knee))
        for p in LEG_PARAMS:
            tracks[f"{side}_{p}"] = PchipInterpolator(key_t, [k[p] for k in keys])(times)
    return tracks


def _rotvecs(tracks: dict[str, np.ndarray]) -> np.ndarray:
    frames = len(tracks["pelvis_pitch"])
    rv = np.zeros((frames, 22, 3))

    def about_x(angle):
        return np.stack([angle, np.zeros_like(angle), np.zeros_like(angle)], axis=-1)

    root = quat.multiply(BODY_TO_WORLD, quat.from_axis_angle(about_x(tracks["pelvis_pitch"])))
    rv[:, J["pelvis"]] = quat.to_axis_angle(root)
    for spine in ("spine1", "spine2", "spine3"):
        rv[:, J[spine]] = about_x(tracks["spine_lean"] / 3.0)
    # The hips also undo the pelvis pitch so hip_flex is the thigh's angle to the vertical.
    for side in SIDES:
        rv[:, J[f"{side}_hip"]] = about_x(tracks[f"{side}_hip_flex"] - tracks["pelvis_pitch"])
        rv[:, J[f"{side}_knee"]] = about_x(tracks[f"{side}_knee_flex"])
        rv[:, J[f"{side}_ankle"]] = about_x(tracks[f"{side}_ankle_flex"])
    # Arms: from the T-pose down to the sides (about the body z), then swung about x.
    for side, down in (("left", -1.35), ("right", 1.35)):
        swing = quat.from_axis_angle(about_x(tracks["arm_swing"] - tracks["spine_lean"] - tracks["pelvis_pitch"]))
        lower = quat.from_axis_angle(np.array([0.0, 0.0, down]))
        rv[:, J[f"{side}_shoulder"]] = quat.to_axis_angle(quat.multiply(swing, np.broadcast_to(lower, swing.shape)))
        # Elbow bend: the forearm folds forward, about the upper arm's local y once arms are down.
        sign = 1.0 if side == "left" else -1.0
        rv[:, J[f"{side}_elbow"], 1] = sign * tracks["elbow_flex"]
    return rv


def _pose_only_fk(tracks: dict[str, np.ndarray], rest: np.ndarray) -> np.ndarray:
    """Joint positions (T, 22, 3) relative to the SMPL origin (trans = 0)."""
    rv = _rotvecs(tracks)
    return smpl.forward_kinematics(rv, np.zeros((len(rv), 3)), rest)[0]


def _sole_height(pos: np.ndarray, clearance: dict[str, float]) -> np.ndarray:
    return np.minimum(pos[:, [7, 8], 2].min(1) - clearance["ankle"], pos[:, [10, 11], 2].min(1) - clearance["foot"])


def _feet_x(pos: np.ndarray) -> np.ndarray:
    return pos[:, [7, 8, 10, 11], 0].mean(axis=1)


def _flat_foot_ankle(hip, knee):
    """Ankle flexion that keeps the foot at its rest pitch: hip, knee and ankle turn about the same axis."""
    return -(hip + knee)


def _set_legs(tracks: dict[str, np.ndarray], frames: np.ndarray, side: str, hip: np.ndarray, knee: np.ndarray) -> None:
    """One leg's angles on `frames`, with the ankle keeping the foot flat (its rest pitch)."""
    tracks[f"{side}_hip_flex"][frames] = hip
    tracks[f"{side}_knee_flex"][frames] = knee
    tracks[f"{side}_ankle_flex"][frames] = _flat_foot_ankle(hip, knee)


def _solve_leg(tracks: dict[str, np.ndarray], frames: np.ndarray, side: str, trans: np.ndarray,
               ankle_target: np.ndarray, rest: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Hip and knee flexion of one leg on `frames` that put its ankle at `ankle_target` (F, 3; x and z
    are matched) for the given root translations: Newton's method with a finite-difference
    Jacobian, all frames at once."""
    ankle_joint = J[f"{side}_ankle"]
    q = np.stack([tracks[f"{side}_hip_flex"][frames], tracks[f"{side}_knee_flex"][frames]], axis=-1)

    def ankle(qs):
        sub = {k: v[frames].copy() for k, v in tracks.items()}
        _set_legs(sub, slice(None), side, qs[:, 0], qs[:, 1])
        return (_pose_only_fk(sub, rest)[:, ankle_joint] + trans)[:, [0, 2]]

    goal = ankle_target[:, [0, 2]]
    for _ in range(iterations):
        residual = ankle(q) - goal
        jac = np.empty((len(frames), 2, 2))
        for j in range(2):
            dq = np.zeros(2)
            dq[j] = 1e-5
            jac[:, :, j] = (ankle(q + dq) - goal - residual) / 1e-5
        # Damped: a full Newton step from a near-straight knee can jump to the other branch of the leg.
        q = q - np.clip(np.linalg.solve(jac, residual[..., None])[..., 0], -0.2, 0.2)
    miss = np.abs(ankle(q) - goal).max()
    if miss > 1e-4:  # only the authoring constants can cause this
        raise ValueError(f"sample: the {side} leg cannot reach its pinned foot (miss {miss:.3f} m)")
    return q[:, 0], q[:, 1]


def _pitch_whole_body(tracks: dict[str, np.ndarray], frames, angle) -> None:
    """Lean the whole body forward by `angle` on `frames`, limbs and all (hips and arms are keyed
    against the world's vertical, so they turn with the pelvis by the same angle)."""
    for name in ("pelvis_pitch", "arm_swing", *(f"{side}_hip_flex" for side in SIDES)):
        tracks[name][frames] += angle


def _spin_free_flight(tracks: dict[str, np.ndarray], flight: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """The whole-body lean (rad, per frame of `flight`, take-off to touch-down) that keeps the body's
    angular momentum about its centre of mass constant in the air, as nothing outside it can change it,
    and is 0 at both ends, so the take-off and touch-down poses stay as planned. Without it the keyed
    swing of arms and legs would turn a flight no body can make: on the G1 the reference's pitch
    momentum swung between -13 and +3 kg m^2/s in the air (0.4 s)."""
    dt = 1.0 / FPS

    def posed(frame, angle):
        one = {name: track[[frame]].copy() for name, track in tracks.items()}
        _pitch_whole_body(one, slice(None), angle)
        return _pose_only_fk(one, rest)[0]

    def momentum(before, after):  # pitch momentum (about world y) per unit mass between two poses
        return smpl.angular_momentum(np.stack([before, after]), dt)[0, 1]

    def lean(momentum_in_air):
        angles, previous = [0.0], posed(flight[0], 0.0)
        for frame in flight[1:]:
            # the momentum is affine in the next frame's lean (one secant step is exact up to rounding)
            low, high = angles[-1], angles[-1] + 0.1
            m_low, m_high = momentum(previous, posed(frame, low)), momentum(previous, posed(frame, high))
            angles.append(low + (momentum_in_air - m_low) * (high - low) / (m_high - m_low))
            previous = posed(frame, angles[-1])
        return np.array(angles)

    # The lean at touch-down is affine in the momentum too: two tries and a third to land at 0.
    end_a, end_b = lean(0.0)[-1], lean(0.1)[-1]
    return lean(-end_a * 0.1 / (end_b - end_a))


def make_sample_clip() -> SampleClip:
    frames = int(round(DURATION_S * FPS)) + 1
    times = np.arange(frames) / FPS
    push_start = int(round(KEYFRAMES[CROUCH_KEY][0] * FPS))  # the push starts at the bottom of the crouch
    takeoff = int(round(TAKEOFF_S * FPS))
    touchdown = int(round(TOUCHDOWN_S * FPS))
    flight_time = (touchdown - takeoff) / FPS
    tracks = _pose_tracks(times)
    rest = smpl.rest_joints(None)
    clearance = smpl.sole_clearance(rest)
    pos = _pose_only_fk(tracks, rest)
    trans = np.zeros((frames, 3))

    # Up to take-off the feet stand still and the lowest sole is on the floor, so the pose moves the body.
    # Until the push starts that is the clip; from there on it gives the take-off height.
    before = np.arange(takeoff + 1)
    trans[before, 2] = -_sole_height(pos[before], clearance)
    trans[before, 0] = _feet_x(pos[:1])[0] - _feet_x(pos[before])
    posed_com = smpl.center_of_mass(pos[before] + trans[before, None])
    posed_velocity = np.gradient(posed_com, 1.0 / FPS, axis=0)
    ankles = {side: pos[0, J[f"{side}_ankle"]] + trans[0] for side in SIDES}
    ankle_x = np.mean([a[0] for a in ankles.values()])
    ball_x = pos[0, [J["left_foot"], J["right_foot"]], 0].mean() + trans[0, 0]

    # Where the body comes to rest: the final pose standing with its feet JUMP_DISTANCE_M ahead (the
    # feet start at the pose's own x: trans[0] = 0).
    stand = pos[-1] + np.array([_feet_x(pos[:1])[0] + JUMP_DISTANCE_M - _feet_x(pos[-1:])[0], 0.0,
                                -_sole_height(pos[-1:], clearance)[0]])
    # (Knees a little soft, SOFT_KNEES_M lower: straight legs are where the leg solve below is singular.)
    com_rest = smpl.center_of_mass(stand) - np.array([0.0, 0.0, SOFT_KNEES_M])
    # The landing's height: the centre of mass touches down TOUCHDOWN_DROP_M below standing height,
    # still falling at the flight's speed, sinks to ABSORB_DEPTH_M below it and rises back.
    com_takeoff_z = posed_com[takeoff, 2] - TAKEOFF_CROUCH_M
    com_touchdown_z = com_rest[2] - TOUCHDOWN_DROP_M
    vz0 = (com_touchdown_z - com_takeoff_z) / flight_time + 0.5 * GRAVITY * flight_time
    absorb_t, recover_t = KEYFRAMES[-3][0], KEYFRAMES[-2][0]
    landing_height = CubicHermiteSpline(
        [times[touchdown], absorb_t, recover_t, times[-1]],
        [com_touchdown_z, com_rest[2] - ABSORB_DEPTH_M, com_rest[2], com_rest[2]],
        [vz0 - GRAVITY * flight_time, 0.0, 0.0, 0.0])
    after = np.arange(touchdown, frames)

    def land(x_takeoff):
        return balanced_landing(landing_height, times[after], x_takeoff, com_rest[0], flight_time)

    # The push: the centre of mass rises from the crouch's height and speed to the take-off's, and moves
    # forward as the pendulum of its zero-moment point (between a little behind the ankles and the balls of the feet).
    push = np.arange(push_start, takeoff + 1)
    push_height = CubicHermiteSpline([times[push_start], times[takeoff]], [posed_com[push_start, 2], com_takeoff_z],
                                     [posed_velocity[push_start, 2], vz0])
    push_x, vx = planned_push(push_height, times[push], posed_com[push_start, 0], posed_velocity[push_start, 0],
                               (ankle_x - 0.5 * (ball_x - ankle_x), ball_x), land)
    landing_x, _ = land(push_x[-1])

    com = np.zeros((frames, 3))
    com[:, 1] = posed_com[0, 1]  # straight ahead
    com[push, 0] = push_x
    com[push, 2] = push_height(times[push])
    tau = (np.arange(takeoff, touchdown + 1) - takeoff) / FPS
    com[takeoff : touchdown + 1, 0] = push_x[-1] + vx * tau
    com[takeoff : touchdown + 1, 2] = com_takeoff_z + vz0 * tau - 0.5 * GRAVITY * tau**2
    com[after, 0] = landing_x
    com[after, 2] = landing_height(times[after])

    # The legs of the push and of the landing reach the pinned feet (each ankle where it stood before,
    # and where the standing pose has it after) from wherever the planned body is; the take-off and
    # touch-down keys take those legs so the flight's leg swing starts and ends in them. The body's
    # translation depends on the legs (a third of the mass), so alternate a few times.
    grounded = {"push": (push, ankles), "landed": (after, {side: stand[J[f"{side}_ankle"]] for side in SIDES})}
    airborne = np.arange(takeoff + 1, touchdown)

    def place_body(legs):
        """The pose with these pinned legs, and the root translations that put its centre of mass on `com`."""
        keyed = {TAKEOFF_KEY: {side: (h[-1], k[-1]) for side, (h, k) in legs["push"].items()},
                 TOUCHDOWN_KEY: {side: (h[0], k[0]) for side, (h, k) in legs["landed"].items()}} if legs else None
        tracks = _pose_tracks(times, keyed)
        for phase, (phase_frames, _) in grounded.items():
            for side, (hip, knee) in (legs or {}).get(phase, {}).items():
                _set_legs(tracks, phase_frames, side, hip, knee)
        pos = _pose_only_fk(tracks, rest)
        for phase_frames in (push, airborne, after):
            trans[phase_frames] = com[phase_frames] - smpl.center_of_mass(pos[phase_frames])
        return tracks

    legs = {}
    for _ in range(5):
        tracks = place_body(legs)
        legs = {phase: {side: _solve_leg(tracks, phase_frames, side, trans[phase_frames],
                                         np.repeat(targets[side][None], len(phase_frames), axis=0), rest)
                        for side in SIDES}
                for phase, (phase_frames, targets) in grounded.items()}
    tracks = place_body(legs)
    flight = np.arange(takeoff, touchdown + 1)
    _pitch_whole_body(tracks, flight, _spin_free_flight(tracks, flight, rest))
    pos = _pose_only_fk(tracks, rest)
    trans[airborne] = com[airborne] - smpl.center_of_mass(pos[airborne])
    return SampleClip(_rotvecs(tracks).reshape(frames, 66), trans, FPS, takeoff, touchdown)


def write_sample(path: str | Path = SAMPLE_PATH) -> Path:
    """Writes the synthetic far jump as an AMASS-style npz (atomically); returns the path."""
    from pipeline.common.atomic import atomic_file

    clip = make_sample_clip()
    path = Path(path)
    with atomic_file(path) as handle:
        np.savez(
            handle,
            poses=clip.poses.astype(np.float32),
            trans=clip.trans.astype(np.float32),
            betas=np.zeros(10, np.float32),
            mocap_framerate=np.float64(clip.fps),
            gender=np.array("neutral"),
            note=np.array("SYNTHETIC sample authored by pipeline/human/sample.py from keyframe poses; not motion capture"),
        )
    return path


if __name__ == "__main__":
    print(write_sample(sys.argv[1] if len(sys.argv) > 1 else SAMPLE_PATH))
