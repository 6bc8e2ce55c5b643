"""AdaMimic's f_edit (sparse keyframe offsets → D_edit) and Gleicher-style rule editing (D_rule).

Both only translate global poses: root and tracked bodies move by an offset, rotations and local
joint angles stay exactly the original's.

ψ is absolute (jump distance, jump height, step height, hit distance). The total offset is
Δ(ψ) = sign · (ψ − ψ_raw) along the edit direction d:
  * x, y, heading, z_hold — cumulative: with n edited keyframes, each adds Δ/n, and every keyframe
    holds the sum of the edits at or before it (triple jump: landing k moves by k·Δ/3, so ψ is the
    total distance of the three jumps; a single edited landing moves by Δ and everything after
    follows);
  * z_apex — only the edited keyframes (the apex) move by Δ; the keyframes after are back at 0.
d: x → +x, y → +y, heading → the clip's own horizontal travel direction (start → end of the root),
z_* → +z.

Rule editing (D_rule) gives every frame an offset: between two consecutive keyframes (frame 0 with
offset 0 before the first) the offset goes linearly from the earlier keyframe's to the later one's by
the root's progress along the edit direction (for vertical edits, along the root's horizontal
travel between the two keyframes, since height is not monotonic in a jump; by time when the root
hardly moves), clipped to [0, 1]; after the last keyframe it is held. At keyframes it equals D_edit.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.config import CUMULATIVE_MODES, TaskConfig
from pipeline.keyframes.task_parsing import merge_ranges
from pipeline.keyframes.select import KeyframeTable
from pipeline.keyframes.tracking_data import TrackingData
from pipeline.motion.motion import Motion

MODES = ("edit", "rule", "original")
MIN_PROGRESS = 0.02  # m of root travel below which progress falls back to time


def edit_direction(motion: Motion, mode: str) -> np.ndarray:
    """Unit (3,) direction along which ψ moves the keyframes."""
    if mode == "x":
        return np.array([1.0, 0.0, 0.0])
    if mode == "y":
        return np.array([0.0, 1.0, 0.0])
    if mode in ("z_apex", "z_hold"):
        return np.array([0.0, 0.0, 1.0])
    if mode == "heading":
        travel = motion.root_pos[-1, :2] - motion.root_pos[0, :2]
        if np.linalg.norm(travel) < 0.05:  # standing still: fall back to the start's facing (x)
            return np.array([1.0, 0.0, 0.0])
        travel = travel / np.linalg.norm(travel)
        return np.array([travel[0], travel[1], 0.0])
    raise PipelineInputError(motion.source, "edit.mode", f"unknown edit axis {mode!r}")


def keyframe_offsets(motion: Motion, task: TaskConfig, keyframes: KeyframeTable, psi: np.ndarray) -> np.ndarray:
    """(N, K, 3) world translation of every keyframe target for each ψ (f_edit)."""
    psi = np.atleast_1d(np.asarray(psi, float))
    direction = edit_direction(motion, task.edit.mode)
    total = task.edit.sign * (psi - task.psi.raw)  # (N,)
    edited = keyframes.edited.astype(float)
    if task.edit.mode in CUMULATIVE_MODES or task.edit.mode == "z_hold":
        share = np.cumsum(edited) / max(edited.sum(), 1.0)  # (K,) fraction of Δ reached at keyframe k
    else:  # z_apex: the edited keyframes only, then back
        share = edited
    return total[:, None, None] * share[None, :, None] * direction[None, None, :]


def _progress_weight(motion: Motion, task: TaskConfig, a: int, b: int) -> np.ndarray:
    """(b - a + 1,) 0 → 1 weight of frames a..b by the root's progress (see the module note)."""
    root = motion.root_pos[a:b + 1]
    if task.edit.mode in ("z_apex", "z_hold"):
        travel = root[-1, :2] - root[0, :2]
        axis = np.array([*travel, 0.0]) / max(np.linalg.norm(travel), 1e-12)
    else:
        axis = edit_direction(motion, task.edit.mode)
    progress = (root - root[0]) @ axis
    span = progress[-1]
    if abs(span) < MIN_PROGRESS:
        return np.linspace(0.0, 1.0, b - a + 1)
    w = np.clip(progress / span, 0.0, 1.0)
    w[0], w[-1] = 0.0, 1.0
    return w


def dense_offsets(motion: Motion, task: TaskConfig, keyframes: KeyframeTable, offsets: np.ndarray) -> np.ndarray:
    """(N, T, 3) per-frame offsets of the rule-based edit (D_rule), equal to `offsets` at keyframes."""
    n, t = offsets.shape[0], motion.num_frames
    frames = list(keyframes.frames)
    anchors = frames if frames[0] == 0 else [0] + frames
    anchor_off = offsets if frames[0] == 0 else np.concatenate([np.zeros((n, 1, 3)), offsets], axis=1)
    out = np.empty((n, t, 3))
    for i in range(len(anchors) - 1):
        a, b = anchors[i], anchors[i + 1]
        start, end = anchor_off[:, i], anchor_off[:, i + 1]
        if np.array_equal(start, end):
            out[:, a:b + 1] = start[:, None]
            continue
        w = _progress_weight(motion, task, a, b)
        out[:, a:b + 1] = start[:, None] + w[None, :, None] * (end - start)[:, None]
    out[:, anchors[-1]:] = anchor_off[:, -1][:, None]
    out[:, keyframes.frames] = offsets  # exact at keyframes, whatever the float rounding above
    return out


def sample_psi(ranges, num_samples: int, seed: int | None = None) -> np.ndarray:
    """Stratified samples over the union of ranges: one per equal-length stratum (its midpoint, or a
    uniform draw inside it with a seed), so every sub-range gets samples in proportion to its length."""
    merged = merge_ranges(ranges)
    lengths = np.array([hi - lo for lo, hi in merged])
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    if seed is None:
        u = (np.arange(num_samples) + 0.5) / num_samples
    else:
        u = (np.arange(num_samples) + np.random.default_rng(seed).uniform(size=num_samples)) / num_samples
    s = u * cum[-1]
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(merged) - 1)
    return np.array([merged[i][0] for i in idx]) + (s - cum[idx])


def apply_offsets(motion: Motion, offsets: np.ndarray, name: str | None = None) -> Motion:
    """The motion with every frame's root and tracked bodies translated by offsets (T, 3);
    rotations and joints are the original arrays bit for bit."""
    edited = replace(motion, root_pos=motion.root_pos + offsets, body_pos=motion.body_pos + offsets[:, None, :],
                     name=name or motion.name)
    # Motion re-normalises quaternions on construction, which can move their last bit: keep the
    # original (already unit and continuous) ones so the edit is a pure translation.
    edited.root_quat, edited.body_quat = motion.root_quat.copy(), motion.body_quat.copy()
    return edited


def build_tracking_data(motion: Motion, task: TaskConfig, keyframes: KeyframeTable, mode: str = "edit",
                        num_samples: int | None = None, seed: int | None = None) -> TrackingData:
    """D_edit (`edit`: keyframe offsets), D_rule (`rule`: plus dense offsets) or the unedited clip
    (`original`: one sample at ψ_raw, zero offsets) as the environment's `TrackingData`."""
    from pipeline.keyframes.terrain import resolve_terrain

    if mode not in MODES:
        raise PipelineInputError(f"task {task.name}", "mode", f"must be one of {list(MODES)}, got {mode!r}")
    if len(keyframes) == 0 or keyframes.frames[-1] >= motion.num_frames:
        raise PipelineInputError(f"task {task.name}", "keyframes", "keyframe table does not fit the motion")
    if mode == "original":
        psi = np.array([task.psi.raw])
    else:
        psi = sample_psi(task.psi.train, num_samples or task.num_samples, seed)
    offsets = keyframe_offsets(motion, task, keyframes, psi)
    if mode == "original":
        offsets = np.zeros_like(offsets)
    dense = dense_offsets(motion, task, keyframes, offsets) if mode == "rule" else None
    return TrackingData(
        task=task.name,
        motion=motion,
        keyframe_frames=keyframes.frames.copy(),
        keyframe_labels=tuple(keyframes.labels),
        sparse_scale=keyframes.sparse_scale.copy(),
        edited=keyframes.edited.copy(),
        psi=psi,
        keyframe_offsets=offsets,
        dense_offsets=dense,
        psi_raw=task.psi.raw,
        psi_ranges=task.psi.as_ranges(),
        terrain=resolve_terrain(task, motion, keyframes),
    )
