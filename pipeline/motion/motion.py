"""`Motion`: a G1 reference motion, the currency between retargeting, editing, training and eval.

Conventions: world frame z-up, x forward at the clip's start; quaternions (w, x, y, z);
`joint_pos` columns in `joint_names` order; `body_*` arrays over the tracked bodies in
`body_names` order. Velocities are derived from poses by central finite differences
(quaternion-aware for rotations) so they are always consistent with the poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np

from pipeline.common import quat
from pipeline.common.errors import PipelineInputError, check_finite, check_shape


def _central_difference(x: np.ndarray, dt: float) -> np.ndarray:
    if x.shape[0] < 2:
        return np.zeros_like(x)
    return np.gradient(x, dt, axis=0)


@dataclass
class Motion:
    fps: float
    joint_names: tuple[str, ...]
    body_names: tuple[str, ...]
    root_pos: np.ndarray  # (T, 3)
    root_quat: np.ndarray  # (T, 4) wxyz
    joint_pos: np.ndarray  # (T, J)
    body_pos: np.ndarray  # (T, B, 3) world
    body_quat: np.ndarray  # (T, B, 4) world, wxyz
    name: str = "motion"
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self) -> None:
        self.joint_names = tuple(self.joint_names)
        self.body_names = tuple(self.body_names)
        for key in ("root_pos", "root_quat", "joint_pos", "body_pos", "body_quat"):
            setattr(self, key, np.asarray(getattr(self, key), dtype=np.float64))
        self.validate()
        self.root_quat = quat.make_continuous(quat.normalize(self.root_quat))
        self.body_quat = quat.make_continuous(quat.normalize(self.body_quat))

    # ----------------------------------------------------------------------------- checks
    def validate(self) -> None:
        src = self.source
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise PipelineInputError(src, "fps", f"must be a positive number, got {self.fps}")
        t, j, b = self.root_pos.shape[0], len(self.joint_names), len(self.body_names)
        if t < 2:
            raise PipelineInputError(src, "root_pos", f"needs at least 2 frames, got {t}")
        check_shape(self.root_pos, (t, 3), src, "root_pos")
        check_shape(self.root_quat, (t, 4), src, "root_quat")
        check_shape(self.joint_pos, (t, j), src, "joint_pos")
        check_shape(self.body_pos, (t, b, 3), src, "body_pos")
        check_shape(self.body_quat, (t, b, 4), src, "body_quat")
        for key in ("root_pos", "root_quat", "joint_pos", "body_pos", "body_quat"):
            check_finite(getattr(self, key), src, key)
        if np.any(np.linalg.norm(self.root_quat, axis=-1) < 1e-6):
            raise PipelineInputError(src, "root_quat", "contains zero-length quaternions")

    # ----------------------------------------------------------------------------- sizes
    @property
    def num_frames(self) -> int:
        return self.root_pos.shape[0]

    @property
    def dt(self) -> float:
        return 1.0 / self.fps

    @property
    def duration(self) -> float:
        return (self.num_frames - 1) / self.fps

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.num_frames) / self.fps

    # ----------------------------------------------------------------------------- velocities
    @property
    def root_lin_vel(self) -> np.ndarray:
        return _central_difference(self.root_pos, self.dt)

    @property
    def root_ang_vel(self) -> np.ndarray:
        """World-frame angular velocity of the root."""
        return quat.angular_velocity(self.root_quat, self.dt, frame="world")

    @property
    def joint_vel(self) -> np.ndarray:
        return _central_difference(self.joint_pos, self.dt)

    @property
    def body_lin_vel(self) -> np.ndarray:
        return _central_difference(self.body_pos, self.dt)

    @property
    def body_ang_vel(self) -> np.ndarray:
        return quat.angular_velocity(self.body_quat, self.dt, frame="world")

    def qpos(self) -> np.ndarray:
        """(T, 7 + J) MuJoCo generalized positions, joints in `joint_names` order."""
        return np.concatenate([self.root_pos, self.root_quat, self.joint_pos], axis=1)

    def qvel(self) -> np.ndarray:
        """(T, 6 + J) MuJoCo generalized velocities (free joint: world linear, body angular)."""
        body_ang = quat.angular_velocity(self.root_quat, self.dt, frame="body")
        return np.concatenate([self.root_lin_vel, body_ang, self.joint_vel], axis=1)

    # ----------------------------------------------------------------------------- edits
    def slice(self, start: int, stop: int) -> "Motion":
        return replace(
            self,
            root_pos=self.root_pos[start:stop],
            root_quat=self.root_quat[start:stop],
            joint_pos=self.joint_pos[start:stop],
            body_pos=self.body_pos[start:stop],
            body_quat=self.body_quat[start:stop],
        )

    def resample(self, fps: float) -> "Motion":
        """Linear interpolation for positions and joints, slerp for rotations."""
        if fps <= 0:
            raise PipelineInputError(self.source, "fps", f"target fps must be positive, got {fps}")
        n = int(np.floor(self.duration * fps + 1e-9)) + 1
        t = np.arange(n) / fps * self.fps  # in source frames
        i0 = np.clip(np.floor(t).astype(int), 0, self.num_frames - 1)
        i1 = np.clip(i0 + 1, 0, self.num_frames - 1)
        a = t - i0

        def lerp(x):
            shape = (-1,) + (1,) * (x.ndim - 1)
            return x[i0] * (1 - a.reshape(shape)) + x[i1] * a.reshape(shape)

        body_alpha = np.repeat(a[:, None], len(self.body_names), axis=1)
        return replace(
            self,
            fps=float(fps),
            root_pos=lerp(self.root_pos),
            root_quat=quat.slerp(self.root_quat[i0], self.root_quat[i1], a),
            joint_pos=lerp(self.joint_pos),
            body_pos=lerp(self.body_pos),
            body_quat=quat.slerp(self.body_quat[i0], self.body_quat[i1], body_alpha),
        )

    def reorder_joints(self, joint_names: tuple[str, ...]) -> "Motion":
        """Same motion with joint columns in another order, matched by name."""
        missing = [n for n in joint_names if n not in self.joint_names]
        if missing:
            raise PipelineInputError(self.source, "joint_names", f"missing joints {missing}")
        index = [self.joint_names.index(n) for n in joint_names]
        return replace(self, joint_names=tuple(joint_names), joint_pos=self.joint_pos[:, index])

    def body_index(self, name: str) -> int:
        return self.body_names.index(name)

    def save(self, path: str | Path) -> None:
        from pipeline.motion.dataset import write_motions

        write_motions(path, [self])

    @staticmethod
    def load(path: str | Path) -> "Motion":
        from pipeline.motion.dataset import read_motions

        motions = read_motions(path)
        if len(motions) != 1:
            raise PipelineInputError(path, "episodes", f"expected one motion, found {len(motions)}")
        return motions[0]


class RobotKinematics:
    """MuJoCo forward kinematics of the tracked-body sites, from root pose + joint positions."""

    def __init__(self, model: mujoco.MjModel | None = None, config=None):
        from pipeline.robot.g1 import build_model, joint_qpos_indices, load_robot_config, site_ids

        self.config = config or load_robot_config()
        self.model = model if model is not None else build_model(visual=False)
        self.data = mujoco.MjData(self.model)
        self.joint_names = self.config.joint_names
        self.body_names = self.config.tracked_body_names
        self.qpos_index = joint_qpos_indices(self.model, self.joint_names)
        self.site_index = site_ids(self.model, self.config.tracked_site_names)
        self.site_body = self.model.site_bodyid[self.site_index]

    def body_poses(self, root_pos, root_quat, joint_pos) -> tuple[np.ndarray, np.ndarray]:
        root_pos, root_quat, joint_pos = (np.atleast_2d(np.asarray(x, float)) for x in (root_pos, root_quat, joint_pos))
        t = root_pos.shape[0]
        pos = np.empty((t, len(self.site_index), 3))
        rot = np.empty((t, len(self.site_index), 4))
        for i in range(t):
            self.data.qpos[0:3] = root_pos[i]
            self.data.qpos[3:7] = root_quat[i]
            self.data.qpos[self.qpos_index] = joint_pos[i]
            mujoco.mj_kinematics(self.model, self.data)
            pos[i] = self.data.site_xpos[self.site_index]
            # Tracked sites carry no rotation of their own: their frame is their body's.
            rot[i] = self.data.xquat[self.site_body]
        return pos, rot

    def motion(self, fps: float, root_pos, root_quat, joint_pos, name: str = "motion",
               source: str = "<memory>") -> Motion:
        body_pos, body_quat = self.body_poses(root_pos, root_quat, joint_pos)
        return Motion(
            fps=fps,
            joint_names=self.joint_names,
            body_names=self.body_names,
            root_pos=root_pos,
            root_quat=root_quat,
            joint_pos=joint_pos,
            body_pos=body_pos,
            body_quat=body_quat,
            name=name,
            source=source,
        )
