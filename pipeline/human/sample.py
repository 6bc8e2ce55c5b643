"""The bundled sample input: a SYNTHETIC standing far jump, authored here from keyframe poses.

It is not motion capture and not anyone's recording: it exists so `dvc repro` runs on a fresh
clone without the paper's data. `python -m pipeline.human.sample [OUT.npz]` rewrites
`data/sample/far_jump_synthetic.npz` (AMASS-style SMPL parameters, z-up, 30 fps, deterministic).

How it is made:
  * joint rotations: a handful of scalar pose parameters (pelvis pitch, hip/knee/ankle flexion,
    spine lean, arm swing, elbow bend) keyed at stand, crouch, rise, take-off, tuck, landing,
    absorb and recover, interpolated with monotone cubics (no overshoot), turned into SMPL
    local axis-angles of a left-right symmetric body;
  * root translation, by phase: on the ground the feet are pinned (their mean x stays where it
    touched down, the lowest sole point stays on the floor z = 0), so the body moves only by the
    pose; in flight the pelvis follows a true projectile, x(t) = x0 + vx t,
    z(t) = z0 + vz t - g t^2 / 2 with g = 9.81 m/s^2, whose velocity is solved from the take-off
    and touch-down pelvis positions and the flight time;
  * the feet land `JUMP_DISTANCE_M` ahead of where they took off.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from pipeline import REPO_ROOT
from pipeline.common import quat
from pipeline.human import smpl

SAMPLE_PATH = REPO_ROOT / "data" / "sample" / "far_jump_synthetic.npz"
FPS = 30.0
DURATION_S = 2.6
TAKEOFF_S = 0.9
TOUCHDOWN_S = 1.35
JUMP_DISTANCE_M = 1.0
GRAVITY = 9.81

# Pose parameters (radians), SMPL body frame (x left, y up, z front): + about x leans the trunk
# forward / bends the knee / swings the arm back; hip flexion (thigh forward) is negative.
# The crouch, the rise and the absorb bend the knees past the hips (shins tilted forward) so that,
# on the G1, the centre of mass stays over the middle of the feet rather than at the heels, where a
# tracking policy falls over backwards (tests/test_retarget.py::test_bundled_sample_balances_on_the_g1).
PARAMS = ("pelvis_pitch", "spine_lean", "hip_flex", "knee_flex", "ankle_flex", "arm_swing", "elbow_flex")
KEYFRAMES: list[tuple[float, dict[str, float]]] = [
    (0.00, dict(pelvis_pitch=0.00, spine_lean=0.00, hip_flex=0.00, knee_flex=0.00, ankle_flex=0.00, arm_swing=0.0, elbow_flex=0.1)),  # stand
    (0.45, dict(pelvis_pitch=0.55, spine_lean=0.25, hip_flex=-1.05, knee_flex=1.65, ankle_flex=-0.75, arm_swing=1.0, elbow_flex=0.2)),  # crouch, arms back
    (0.73, dict(pelvis_pitch=0.75, spine_lean=0.25, hip_flex=-0.75, knee_flex=1.25, ankle_flex=-0.50, arm_swing=0.2, elbow_flex=0.2)),  # rise, leaning into the jump
    (0.96, dict(pelvis_pitch=0.45, spine_lean=0.10, hip_flex=0.20, knee_flex=0.05, ankle_flex=0.55, arm_swing=-1.9, elbow_flex=0.2)),  # take-off: extended, arms up
    (1.10, dict(pelvis_pitch=0.30, spine_lean=0.15, hip_flex=-1.40, knee_flex=1.50, ankle_flex=0.10, arm_swing=-1.3, elbow_flex=0.4)),  # tuck
    (1.33, dict(pelvis_pitch=0.35, spine_lean=0.25, hip_flex=-0.60, knee_flex=0.45, ankle_flex=-0.10, arm_swing=-0.6, elbow_flex=0.3)),  # touch-down: legs reach
    (1.70, dict(pelvis_pitch=0.60, spine_lean=0.30, hip_flex=-1.30, knee_flex=1.85, ankle_flex=-0.80, arm_swing=-0.9, elbow_flex=0.3)),  # absorb
    (2.30, dict(pelvis_pitch=0.00, spine_lean=0.00, hip_flex=0.00, knee_flex=0.00, ankle_flex=0.00, arm_swing=0.0, elbow_flex=0.1)),  # recover
    (2.60, dict(pelvis_pitch=0.00, spine_lean=0.00, hip_flex=0.00, knee_flex=0.00, ankle_flex=0.00, arm_swing=0.0, elbow_flex=0.1)),  # stand
]
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


def _pose_tracks(times: np.ndarray) -> dict[str, np.ndarray]:
    key_t = np.array([t for t, _ in KEYFRAMES])
    return {p: PchipInterpolator(key_t, [k[p] for _, k in KEYFRAMES])(times) for p in PARAMS}


def _rotvecs(tracks: dict[str, np.ndarray]) -> np.ndarray:
    frames = len(tracks["hip_flex"])
    rv = np.zeros((frames, 22, 3))

    def about_x(angle):
        return np.stack([angle, np.zeros_like(angle), np.zeros_like(angle)], axis=-1)

    root = quat.multiply(BODY_TO_WORLD, quat.from_axis_angle(about_x(tracks["pelvis_pitch"])))
    rv[:, J["pelvis"]] = quat.to_axis_angle(root)
    for spine in ("spine1", "spine2", "spine3"):
        rv[:, J[spine]] = about_x(tracks["spine_lean"] / 3.0)
    # The hips also undo the pelvis pitch so hip_flex is the thigh's angle to the vertical.
    for side in ("left", "right"):
        rv[:, J[f"{side}_hip"]] = about_x(tracks["hip_flex"] - tracks["pelvis_pitch"])
        rv[:, J[f"{side}_knee"]] = about_x(tracks["knee_flex"])
        rv[:, J[f"{side}_ankle"]] = about_x(tracks["ankle_flex"])
    # Arms: from the T-pose down to the sides (about the body z), then swung about x.
    for side, down in (("left", -1.35), ("right", 1.35)):
        swing = quat.from_axis_angle(about_x(tracks["arm_swing"] - tracks["spine_lean"] - tracks["pelvis_pitch"]))
        lower = quat.from_axis_angle(np.array([0.0, 0.0, down]))
        rv[:, J[f"{side}_shoulder"]] = quat.to_axis_angle(quat.multiply(swing, np.broadcast_to(lower, swing.shape)))
        # Elbow bend: the forearm folds forward, about the upper arm's local y once arms are down.
        sign = 1.0 if side == "left" else -1.0
        rv[:, J[f"{side}_elbow"], 1] = sign * tracks["elbow_flex"]
    return rv


def make_sample_clip() -> SampleClip:
    frames = int(round(DURATION_S * FPS)) + 1
    times = np.arange(frames) / FPS
    rv = _rotvecs(_pose_tracks(times))
    rest = smpl.rest_joints(None)
    clearance = smpl.sole_clearance(rest)
    # Pose-only FK (trans = 0): where joints sit relative to the SMPL origin.
    pos, _ = smpl.forward_kinematics(rv, np.zeros((frames, 3)), rest)
    sole = np.minimum(pos[:, [7, 8], 2].min(1) - clearance["ankle"], pos[:, [10, 11], 2].min(1) - clearance["foot"])
    foot_x = pos[:, [7, 8, 10, 11], 0].mean(axis=1)

    takeoff = int(round(TAKEOFF_S * FPS))
    touchdown = int(round(TOUCHDOWN_S * FPS))
    trans = np.zeros((frames, 3))
    trans[:, 2] = -sole  # ground phases: the lowest sole on the floor
    trans[: takeoff + 1, 0] = foot_x[0] - foot_x[: takeoff + 1]  # feet stay where they stand
    trans[touchdown:, 0] = foot_x[0] + JUMP_DISTANCE_M - foot_x[touchdown:]  # ... and where they land
    # Flight: a projectile between the take-off and touch-down root positions.
    flight_time = (touchdown - takeoff) / FPS
    start, end = trans[takeoff], trans[touchdown]
    velocity = (end - start) / flight_time
    velocity[2] += 0.5 * GRAVITY * flight_time
    tau = (np.arange(takeoff, touchdown + 1) - takeoff) / FPS
    flight = start + velocity * tau[:, None]
    flight[:, 2] -= 0.5 * GRAVITY * tau**2
    trans[takeoff : touchdown + 1] = flight
    trans[:, 0] -= trans[0, 0]
    return SampleClip(rv.reshape(frames, 66), trans, FPS, takeoff, touchdown)


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
