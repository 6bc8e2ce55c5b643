"""A lead-in from the stance at rest to a window's first frame, so a task starts where a standing robot is.

`clip: {start_s, end_s, lead_in_s}`: the keyframes stage cuts the window, chooses and edits its
keyframes, then prepends `lead_in_s` seconds that begin in the default pose at rest (the stance the
balance policy holds, at the window's start position and heading, on the ground under it), hold it a
fifth of the time, and move to the window's first frame with a smoothstep in the root position, the
joints and (slerp) the root orientation. Keyframe frames shift by the lead-in's length; D_rule's
per-frame offsets hold their first value over it; keyframes.json records the lead-in beside the
window. Evaluation and every start at t = 0 then begin at the stance.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from pipeline.keyframes.tracking_data import TrackingData
from pipeline.motion.motion import Motion, RobotKinematics

HOLD_SHARE = 0.2  # of the lead-in, standing still before moving


def _yaw_only(quat_wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = quat_wxyz
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def lead_in_motion(first: Motion, frames: int, kinematics: RobotKinematics | None = None) -> Motion:
    """`frames` frames from the stance at rest to `first`'s frame 0 (not included)."""
    kin = kinematics or RobotKinematics()
    robot = kin.config
    feet = [robot.tracked_body_names.index(name) for name in ("left_ankle", "right_ankle")]
    stance_root = np.array([first.root_pos[0, 0], first.root_pos[0, 1], robot.default_root_height])
    stance_quat = _yaw_only(first.root_quat[0])
    stance_pos, _ = kin.body_poses(stance_root, stance_quat, robot.default_joint_pos)
    # on the ground the window starts on: its lowest foot where the stance's lowest foot is
    stance_root[2] += first.body_pos[0, feet, 2].min() - stance_pos[0, feet, 2].min()
    hold = int(round(HOLD_SHARE * frames))
    s = np.clip((np.arange(frames) - hold) / max(frames - hold, 1), 0.0, 1.0)
    s = s * s * (3.0 - 2.0 * s)  # smoothstep: at rest at both ends
    root = stance_root + s[:, None] * (first.root_pos[0] - stance_root)
    joints = robot.default_joint_pos + s[:, None] * (first.joint_pos[0] - robot.default_joint_pos)
    wxyz = np.stack([stance_quat, first.root_quat[0]])
    slerp = Slerp([0.0, 1.0], Rotation.from_quat(wxyz[:, [1, 2, 3, 0]]))
    quat = slerp(s).as_quat()[:, [3, 0, 1, 2]]
    return kin.motion(first.fps, root, quat, joints, name=f"{first.name}_lead_in", source=first.source)


def concat(a: Motion, b: Motion) -> Motion:
    fields = ("root_pos", "root_quat", "joint_pos", "body_pos", "body_quat")
    return dataclasses.replace(b, **{f: np.concatenate([getattr(a, f), getattr(b, f)]) for f in fields})


def with_lead_in(data: TrackingData, seconds: float) -> TrackingData:
    """`data` with the lead-in prepended (module docstring); unchanged for 0 s."""
    frames = int(round(seconds * data.motion.fps))
    if frames <= 0:
        return data
    motion = data.motion
    if tuple(motion.joint_names) != RobotKinematics().joint_names:
        raise ValueError("with_lead_in: the motion's joints must be in the robot's order")
    dense = data.dense_offsets
    if dense is not None:
        dense = np.concatenate([np.repeat(dense[:, :1], frames, axis=1), dense], axis=1)
    return dataclasses.replace(data, motion=concat(lead_in_motion(motion, frames), motion),
                               keyframe_frames=np.asarray(data.keyframe_frames) + frames, dense_offsets=dense)
