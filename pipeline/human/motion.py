"""`HumanMotion`: a human clip as the SMPL body skeleton, in the pipeline's world frame.

World frame: z up, metres, the person starts facing +x (importers rotate the clip so).
Joints are the 22 SMPL body joints (no hands) in SMPL order, named as in `SMPL_JOINT_NAMES`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.common.errors import PipelineInputError, check_finite, check_shape

SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)
SMPL_PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)


@dataclass
class HumanMotion:
    fps: float
    joint_pos: np.ndarray  # (T, 22, 3) global joint positions, world frame
    joint_quat: np.ndarray  # (T, 22, 4) global joint orientations (wxyz), world frame
    local_rotvec: np.ndarray  # (T, 22, 3) SMPL local axis-angle (root: global orient in world frame)
    root_trans: np.ndarray  # (T, 3) SMPL translation in world frame
    betas: np.ndarray = field(default_factory=lambda: np.zeros(10))
    height: float = 1.7  # standing height of the subject, metres (for robot size scaling)
    name: str = "human"
    source: str = "<memory>"
    joint_names: tuple[str, ...] = SMPL_JOINT_NAMES

    def __post_init__(self) -> None:
        for key in ("joint_pos", "joint_quat", "local_rotvec", "root_trans", "betas"):
            setattr(self, key, np.asarray(getattr(self, key), dtype=np.float64))
        src, t, j = self.source, self.joint_pos.shape[0], len(self.joint_names)
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise PipelineInputError(src, "fps", f"must be a positive number, got {self.fps}")
        check_shape(self.joint_pos, (t, j, 3), src, "joint_pos")
        check_shape(self.joint_quat, (t, j, 4), src, "joint_quat")
        check_shape(self.local_rotvec, (t, j, 3), src, "local_rotvec")
        check_shape(self.root_trans, (t, 3), src, "root_trans")
        for key in ("joint_pos", "joint_quat", "local_rotvec", "root_trans", "betas"):
            check_finite(getattr(self, key), src, key)

    @property
    def num_frames(self) -> int:
        return self.joint_pos.shape[0]

    @property
    def duration(self) -> float:
        return (self.num_frames - 1) / self.fps

    def joint_index(self, name: str) -> int:
        return self.joint_names.index(name)
