"""From SMPL parameters in a source's world frame to a `HumanMotion` in the pipeline's frame.

Pipeline frame: z up, the floor at z = 0, the pelvis above the origin at the first frame, and the
person facing +x at the start (mean facing over the first `FACING_WINDOW_S` seconds).

Conversion, as one rigid rotation C (up fix, then yaw) plus a translation s:
  1. up axis: gravity's axis of the source (e.g. +y for GVHMR and most camera-frame tools, +z for
     AMASS). Given by the format, or found from the data: the mean of pelvis - mid-ankle over the
     clip points up; we snap it to the nearest signed axis (gravity is an axis of the source frame;
     the body's lean must not tilt the world). C_up is the shortest rotation taking it to +z.
  2. facing: the pelvis' front (+z of the SMPL body frame) at the start, projected on the floor;
     C_yaw turns it to +x.
  3. floor: the lowest supporting sole over the clip (1st percentile of the per-frame lowest sole
     point, from ankle/foot joints minus their rest height above the sole) goes to z = 0; a step
     up or down therefore keeps its height relative to the lower level.

SMPL parameters transform so FK in the new frame equals C @ (old FK) + s:
  global_orient' = C * global_orient      (body-frame local rotations are unchanged)
  trans' = C (J0 + trans) + s - J0        (SMPL rotates the root about the rest pelvis J0)
Global joint orientations (joint_quat) are C * R_global: at the SMPL rest pose a joint frame has
the body's up along its local +y and its front along local +z (not the world's z/x).
"""

from __future__ import annotations

import numpy as np

from pipeline.common import quat
from pipeline.common.errors import PipelineInputError, check_finite, check_shape
from pipeline.human import smpl
from pipeline.human.motion import HumanMotion

FACING_WINDOW_S = 0.3
MIN_DURATION_S = 1.0
FLOOR_PERCENTILE = 1.0
AXES = {"+x": (0, 1.0), "-x": (0, -1.0), "+y": (1, 1.0), "-y": (1, -1.0), "+z": (2, 1.0), "-z": (2, -1.0)}


def detect_up_axis(joint_pos: np.ndarray) -> str:
    """Signed axis ('+y', '+z', ...) along which the pelvis sits above the ankles on average."""
    up = np.mean(joint_pos[:, 0] - 0.5 * (joint_pos[:, 7] + joint_pos[:, 8]), axis=0)
    axis = int(np.argmax(np.abs(up)))
    return ("+" if up[axis] >= 0 else "-") + "xyz"[axis]


def up_rotation(up_axis: str) -> np.ndarray:
    """Quaternion of the shortest rotation taking the signed axis `up_axis` to +z."""
    index, sign = AXES[up_axis]
    up = np.zeros(3)
    up[index] = sign
    z = np.array([0.0, 0.0, 1.0])
    if up @ z > 0.5:
        return np.array([1.0, 0.0, 0.0, 0.0])
    if up @ z < -0.5:
        return np.array([0.0, 1.0, 0.0, 0.0])  # 180 degrees about x
    axis = np.cross(up, z)  # unit: up is perpendicular to z here
    return quat.from_axis_angle(axis * (np.pi / 2))


def validate_smpl_arrays(source, fps, local_rotvec, trans, betas) -> None:
    """Raises PipelineInputError naming the field for shapes, NaN/inf, fps and clip length."""
    if not np.isscalar(fps) and np.ndim(fps) != 0:
        raise PipelineInputError(source, "fps", f"expected a number, got shape {np.shape(fps)}")
    fps = float(fps)
    if not np.isfinite(fps) or fps <= 0:
        raise PipelineInputError(source, "fps", f"must be a positive number, got {fps}")
    check_shape(local_rotvec, (None, smpl.NUM_BODY_JOINTS, 3), source, "poses")
    check_shape(trans, (local_rotvec.shape[0], 3), source, "trans")
    check_shape(betas, (None,), source, "betas")
    check_finite(local_rotvec, source, "poses")
    check_finite(trans, source, "trans")
    check_finite(betas, source, "betas")
    frames = local_rotvec.shape[0]
    if frames < 2 or (frames - 1) / fps < MIN_DURATION_S:
        raise PipelineInputError(
            source, "poses", f"clip is {frames} frames at {fps:g} fps, shorter than {MIN_DURATION_S:g} s"
        )


def human_motion_from_smpl(
    *,
    local_rotvec: np.ndarray,
    trans: np.ndarray,
    betas: np.ndarray,
    fps: float,
    source: str,
    name: str,
    up_axis: str | None = None,
    rest: np.ndarray | None = None,
    height: float | None = None,
) -> HumanMotion:
    """Validates, converts to the pipeline frame and runs FK. `up_axis=None` detects it."""
    local_rotvec = np.asarray(local_rotvec, dtype=np.float64)
    trans = np.asarray(trans, dtype=np.float64)
    betas = np.asarray(betas, dtype=np.float64).reshape(-1)
    validate_smpl_arrays(source, fps, local_rotvec, trans, betas)
    fps = float(fps)
    if rest is None:
        rest = smpl.rest_joints(betas)
    if height is None:
        height = smpl.standing_height(betas)

    raw_pos, raw_rot = smpl.forward_kinematics(local_rotvec, trans, rest)
    if up_axis is None:
        up_axis = detect_up_axis(raw_pos)
    c_up = up_rotation(up_axis)
    window = max(1, int(round(FACING_WINDOW_S * fps)))
    front = quat.rotate(quat.multiply(c_up, raw_rot[:window, 0]), smpl.BODY_FRONT).mean(axis=0)
    if np.hypot(front[0], front[1]) < 1e-6:
        raise PipelineInputError(source, "poses", "cannot find the facing direction: the pelvis faces straight up/down")
    c = quat.multiply(quat.from_yaw(-np.arctan2(front[1], front[0])), c_up)

    pos = quat.rotate(c, raw_pos)
    clearance = smpl.sole_clearance(rest)
    sole = np.minimum(
        pos[:, [7, 8], 2].min(axis=1) - clearance["ankle"], pos[:, [10, 11], 2].min(axis=1) - clearance["foot"]
    )
    shift = -np.array([pos[0, 0, 0], pos[0, 0, 1], np.percentile(sole, FLOOR_PERCENTILE)])
    pos = pos + shift

    root_q = quat.multiply(c, quat.from_axis_angle(local_rotvec[:, 0]))
    new_rotvec = local_rotvec.copy()
    new_rotvec[:, 0] = quat.to_axis_angle(root_q)
    new_trans = quat.rotate(c, rest[0] + trans) + shift - rest[0]
    joint_quat = quat.make_continuous(quat.multiply(c, raw_rot))
    return HumanMotion(
        fps=fps,
        joint_pos=pos,
        joint_quat=joint_quat,
        local_rotvec=new_rotvec,
        root_trans=new_trans,
        betas=betas,
        height=float(height),
        name=name,
        source=source,
    )
