"""`TrackingData`: what the environment tracks for one task — the contract between the keyframes
stage (which builds it from D_edit / D_rule) and the environment, training and evaluation.

Edits are pure translations of global poses (AdaMimic's f_edit), so an edited target is the
original pose plus an offset: body_pos[frame] + offset, body_quat unchanged, local joints unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.motion.motion import Motion


@dataclass
class TrackingData:
    task: str
    motion: Motion  # original reference at the control rate (50 fps): dense local targets
    keyframe_frames: np.ndarray  # (K,) int, increasing frame indices into `motion`
    keyframe_labels: tuple[str, ...]  # (K,) "" or a semantic label (takeoff, apex, landing, hit, ...)
    sparse_scale: np.ndarray  # (K,) multiplier of the sparse reward at each keyframe (1 or e.g. 50)
    edited: np.ndarray  # (K,) bool, keyframes moved by the edit
    psi: np.ndarray  # (N,) task variable of each augmented sample (metres)
    keyframe_offsets: np.ndarray  # (N, K, 3) world translation of each keyframe target
    dense_offsets: np.ndarray | None = None  # (N, T, 3) per-frame offsets (D_rule); None for D_edit
    psi_raw: float = 0.0  # the unedited clip's task variable
    psi_ranges: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # train/easy/hard
    terrain: dict = field(default_factory=dict)  # the task's terrain declaration (keyframes.terrain)
    # A push added to the zero action per ψ (priors/push_prior.py: PushPrior), or None; the DVC stage
    # `push_prior` writes it beside D_edit, the stages attach it after loading.
    push_prior: object | None = None

    @property
    def num_keyframes(self) -> int:
        return len(self.keyframe_frames)

    @property
    def num_samples(self) -> int:
        return len(self.psi)

    def offsets_at_frames(self, sample: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Global offset of the reference at `frames` for samples `sample` (both (n,)): the dense
        offset when a rule-based (dense) set is loaded, else the offset of the latest keyframe
        at or before the frame (zero before the first)."""
        if self.dense_offsets is not None:
            return self.dense_offsets[sample, frames]
        k = np.searchsorted(self.keyframe_frames, frames, side="right") - 1
        out = self.keyframe_offsets[sample, np.maximum(k, 0)]
        return np.where((k >= 0)[:, None], out, 0.0)
