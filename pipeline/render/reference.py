"""The edited reference of an export, posed at a phase, for drawing as a ghost beside the robot.

The export's metadata holds the unedited reference pose per frame (`reference.root_pos`, `root_quat`,
`joint_pos`) and the ψ edit at each keyframe (`keyframes.offsets` on `keyframes.psi_grid`). The ghost's root
moves by the edit interpolated linearly between keyframes (held before the first and after the last), so it
flies with the robot to the edited landing instead of jumping there at the landing frame. Exports made before
the pose was stored have no ghost (`ReferencePose.from_metadata` returns None).
"""

from __future__ import annotations

import mujoco
import numpy as np


class ReferencePose:
    def __init__(self, root_pos, root_quat, joint_pos, joint_names, keyframe_frames, keyframe_offsets_grid, psi_grid):
        self.root_pos, self.root_quat = np.asarray(root_pos, float), np.asarray(root_quat, float)
        self.joint_pos = np.asarray(joint_pos, float)
        self.joint_names = tuple(joint_names)
        self.keyframe_frames = np.asarray(keyframe_frames, float)
        self.offsets_grid = np.asarray(keyframe_offsets_grid, float)  # (G, K, 3)
        self.psi_grid = np.asarray(psi_grid, float)
        self.num_frames = len(self.root_pos)
        self._qpos_index = None

    @classmethod
    def from_metadata(cls, meta: dict) -> "ReferencePose | None":
        reference, keyframes = meta.get("reference", {}), meta["keyframes"]
        if "root_pos" not in reference:
            return None
        return cls(reference["root_pos"], reference["root_quat"], reference["joint_pos"], meta["joint_names"],
                   keyframes["frames"], keyframes["offsets"], keyframes["psi_grid"])

    def root_offset(self, psi: float) -> np.ndarray:
        """(T, 3): the ψ edit of the root at every frame."""
        from pipeline.export.sim2sim import _interp_grid

        at_keyframes = _interp_grid(self.psi_grid, self.offsets_grid, psi)  # (K, 3)
        frames = np.arange(self.num_frames)
        return np.stack([np.interp(frames, self.keyframe_frames, at_keyframes[:, i]) for i in range(3)], axis=1)

    def qpos(self, model: mujoco.MjModel, psi: float, phase: float) -> np.ndarray:
        """The model's qpos (the G1 alone: root then joints) of the edited reference at `phase` in [0, 1]."""
        if self._qpos_index is None:
            self._qpos_index = np.array([model.jnt_qposadr[model.joint(n).id] for n in self.joint_names])
            self._offsets = {}
        if psi not in self._offsets:
            self._offsets[psi] = self.root_offset(psi)
        frame = int(np.clip(np.rint(phase * (self.num_frames - 1)), 0, self.num_frames - 1))
        qpos = np.zeros(model.nq)
        qpos[0:3] = self.root_pos[frame] + self._offsets[psi][frame]
        qpos[3:7] = self.root_quat[frame]
        qpos[self._qpos_index] = self.joint_pos[frame]
        return qpos
