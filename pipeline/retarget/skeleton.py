"""Human skeleton -> IK targets with the G1's proportions ("scaled human keypoints").

Uniform scaling (GMR's root-relative scale) leaves targets the robot cannot reach: its thighs,
shins and arms have other length ratios than a person's, and its trunk is rigid from pelvis to
chest (waist roll/pitch locked). So the targets are built as a skeleton transfer:

  * the pelvis follows the human pelvis, its translation scaled by `scale` (jump distance and
    height scale with it);
  * children of the rigid trunk (hips, torso, head, collars, shoulders) sit at the robot's own
    offsets, rotated by the human trunk orientation (a blend of pelvis and chest, `trunk_blend`,
    plus the chest's yaw for the parts above the waist-yaw joint);
  * limb bones (hip->knee->ankle, shoulder->elbow->wrist) keep the human bone's direction and take
    the robot bone's length.

The keypoint error of the quality report is measured against these targets, root-relative.
SMPL joint frames: x = the body's left, y = up, z = forward (checked on the shared clips).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from pipeline.common import quat
from pipeline.human.motion import HumanMotion

# SMPL joint frame (x left, y up, z forward) -> robot body frame (x forward, y left, z up).
_SMPL_REST = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
SMPL_REST_QUAT = quat.from_matrix(_SMPL_REST)

TRUNK_CHILDREN = ("left_hip", "right_hip", "torso")
CHEST_CHILDREN = ("head", "left_collar", "right_collar", "left_shoulder", "right_shoulder")
LIMB_PARENT = {
    "left_knee": "left_hip", "left_ankle": "left_knee",
    "right_knee": "right_hip", "right_ankle": "right_knee",
    "left_elbow": "left_shoulder", "left_wrist": "left_elbow",
    "right_elbow": "right_shoulder", "right_wrist": "right_elbow",
}
ORIENTED_BONES = ("left_knee", "right_knee", "left_ankle", "right_ankle")
# Which SMPL joint each robot keypoint stands for when the task table does not say.
DEFAULT_HUMAN_JOINT = {
    "pelvis": "pelvis", "torso": "spine1", "head": "head",
    **{k: k for k in ("left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
                      "left_collar", "right_collar", "left_shoulder", "right_shoulder",
                      "left_elbow", "right_elbow", "left_wrist", "right_wrist")},
}
CHEST_JOINT = "spine3"


@dataclass(frozen=True)
class RobotGeometry:
    """The G1's keypoint offsets and bone lengths, read from the model at zero joint angles."""

    names: tuple[str, ...]
    rest_pos: np.ndarray  # (K, 3) keypoints with the root at the origin, identity orientation
    rest_quat: np.ndarray  # (K, 4) body orientations at zero joint angles
    trunk_offsets: dict[str, np.ndarray]  # in the pelvis frame
    chest_offsets: dict[str, np.ndarray]  # in the torso frame
    bone_lengths: dict[str, float]  # child keypoint -> length of the bone from its parent
    rest_dirs: dict[str, np.ndarray]  # child keypoint -> unit bone direction at zero joint angles
    ankle_height: float  # ankle keypoint above the sole when the foot is flat
    height: float  # head keypoint above the sole, standing straight

    @staticmethod
    def from_model(model: mujoco.MjModel, names: tuple[str, ...], site_ids: np.ndarray) -> "RobotGeometry":
        data = mujoco.MjData(model)
        data.qpos[:] = 0.0
        data.qpos[3] = 1.0
        mujoco.mj_kinematics(model, data)
        pos = data.site_xpos[site_ids].copy()
        rot = data.xquat[model.site_bodyid[site_ids]].copy()
        i = {n: k for k, n in enumerate(names)}
        pelvis, torso = pos[i["pelvis"]], pos[i["torso"]]
        torso_rot = quat.to_matrix(rot[i["torso"]])
        trunk = {n: pos[i[n]] - pelvis for n in TRUNK_CHILDREN}
        chest = {n: torso_rot.T @ (pos[i[n]] - torso) for n in CHEST_CHILDREN}
        bones = {c: float(np.linalg.norm(pos[i[c]] - pos[i[p]])) for c, p in LIMB_PARENT.items()}
        dirs = {c: (pos[i[c]] - pos[i[p]]) / bones[c] for c, p in LIMB_PARENT.items()}
        sole = foot_sole_height(model, data, model.site_bodyid[site_ids[i["left_ankle"]]])
        return RobotGeometry(
            names=names, rest_pos=pos, rest_quat=rot, trunk_offsets=trunk, chest_offsets=chest,
            bone_lengths=bones, rest_dirs=dirs, ankle_height=float(pos[i["left_ankle"], 2] - sole),
            height=float(pos[i["head"], 2] - sole),
        )


def foot_sole_height(model: mujoco.MjModel, data: mujoco.MjData, body_id: int) -> float:
    """Lowest point of a body's collision geoms (spheres, capsules, boxes) in world z."""
    lowest = np.inf
    for g in np.flatnonzero(model.geom_bodyid == body_id):
        lowest = min(lowest, geom_lowest_z(model.geom_type[g], model.geom_size[g], data.geom_xpos[g],
                                           data.geom_xmat[g].reshape(3, 3)))
    return float(lowest)


def geom_lowest_z(gtype: int, size: np.ndarray, pos: np.ndarray, mat: np.ndarray) -> float:
    if gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
        return pos[2] - size[0]
    if gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return pos[2] - abs(mat[2, 2]) * size[1] - size[0]
    if gtype == mujoco.mjtGeom.mjGEOM_BOX:
        return pos[2] - np.abs(mat[2, :]) @ size[:3]
    return pos[2]


@dataclass
class ScaledTargets:
    """Per-frame IK targets for every robot keypoint (world frame)."""

    pos: np.ndarray  # (T, K, 3)
    quat: np.ndarray  # (T, K, 4) wxyz
    scale: float


def robot_equivalent(human_quat: np.ndarray) -> np.ndarray:
    """Human joint orientation expressed as a robot body orientation (same physical heading)."""
    return quat.normalize(quat.multiply(human_quat, quat.conjugate(SMPL_REST_QUAT)))


def body_scale(human: HumanMotion, mode: str, robot_height: float, fixed_scale: float) -> float:
    return robot_height / human.height if mode == "height" else fixed_scale


def transfer_skeleton(human: HumanMotion, geometry: RobotGeometry, scale: float, trunk_blend: float,
                      human_joint_of: dict[str, str] | None = None) -> ScaledTargets:
    names = geometry.names
    joint_of = dict(DEFAULT_HUMAN_JOINT)
    joint_of.update(human_joint_of or {})
    hp = human.joint_pos
    hj = {n: human.joint_index(joint_of[n]) for n in names}
    t = human.num_frames
    k = {n: i for i, n in enumerate(names)}

    pelvis_q = robot_equivalent(human.joint_quat[:, human.joint_index("pelvis")])
    chest_q = robot_equivalent(human.joint_quat[:, human.joint_index(CHEST_JOINT)])
    chest_q = np.where(np.sum(chest_q * pelvis_q, -1, keepdims=True) < 0, -chest_q, chest_q)
    trunk_q = quat.slerp(pelvis_q, chest_q, np.full(t, trunk_blend))
    # Above the waist-yaw joint the robot can twist: add the chest's yaw relative to the trunk.
    rel = quat.multiply(quat.conjugate(trunk_q), chest_q)
    upper_q = quat.multiply(trunk_q, quat.from_yaw(quat.yaw(rel)))

    pos = np.zeros((t, len(names), 3))
    rot = np.zeros((t, len(names), 4))
    pos[:, k["pelvis"]] = scale * hp[:, hj["pelvis"]]
    for n in TRUNK_CHILDREN:
        pos[:, k[n]] = pos[:, k["pelvis"]] + quat.rotate(trunk_q, np.broadcast_to(geometry.trunk_offsets[n], (t, 3)))
    for n in CHEST_CHILDREN:
        pos[:, k[n]] = pos[:, k["torso"]] + quat.rotate(upper_q, np.broadcast_to(geometry.chest_offsets[n], (t, 3)))
    for child in ("left_knee", "right_knee", "left_ankle", "right_ankle",
                  "left_elbow", "right_elbow", "left_wrist", "right_wrist"):
        parent = LIMB_PARENT[child]
        if child in ORIENTED_BONES:
            # Legs: both skeletons stand straight at rest, so the bone turns with the human parent
            # joint from the robot's own rest direction (the G1 thigh is not straight hip->knee).
            d = quat.rotate(robot_equivalent(human.joint_quat[:, hj[parent]]),
                            np.broadcast_to(geometry.rest_dirs[child], (t, 3)))
        else:
            # Arms: the human rests in a T-pose, the robot arms down with bent elbows; follow the
            # human bone's direction instead.
            d = hp[:, hj[child]] - hp[:, hj[parent]]
            d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
        pos[:, k[child]] = pos[:, k[parent]] + geometry.bone_lengths[child] * d

    for n in names:
        if n in ("pelvis", "left_hip", "right_hip"):
            body_q = trunk_q
        elif n in ("torso",) + CHEST_CHILDREN:
            body_q = upper_q
        else:
            body_q = robot_equivalent(human.joint_quat[:, hj[n]])
        rot[:, k[n]] = quat.multiply(body_q, np.broadcast_to(geometry.rest_quat[k[n]], (t, 4)))
    return ScaledTargets(pos=pos, quat=quat.normalize(rot), scale=scale)
