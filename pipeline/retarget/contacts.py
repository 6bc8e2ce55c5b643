"""Foot contacts from the human clip, and the ground / anti-skate corrections they drive.

Contact: the foot is slow and either low (near the clip's floor) or still for long enough that it
must be standing on something (a step or box: a foot in flight is never still for `still_s`).
Per contact run the foot gets a pin: a fixed position (flat on its support, scaled elevation) and a
yaw. Targets between runs are shifted by a correction interpolated between the neighbouring pins,
so the swing and flight phases (the jump) keep their shape and scaled size.

These contacts say where to pin a foot flat before the IK, not when the body flies: a toe-off or a heel
strike is left free here. Flights (the keyframes', quality.json's `jump`) come from the retargeted
reference's own feet, `motion/feet.py`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.common import quat
from pipeline.human.motion import HumanMotion
from pipeline.motion.feet import runs
from pipeline.retarget.config import ContactConfig

FEET = (("left_ankle", "left_foot"), ("right_ankle", "right_foot"))  # (ankle, toe-base) SMPL joints
RAMP_FRAMES = 3  # source frames over which a foot eases into / out of its flat pinned pose
STILL_S = 0.3  # s; a foot this long without moving is supported, whatever its height


def _clean(mask: np.ndarray, min_frames: int) -> np.ndarray:
    mask = mask.copy()
    for a, b in runs(~mask):  # fill short gaps (a flicker in the middle of a stance)
        if 0 < a and b < len(mask) and b - a < min_frames:
            mask[a:b] = True
    for a, b in runs(mask):  # drop short runs (a foot brushing the floor mid-swing)
        if b - a < min_frames:
            mask[a:b] = False
    return mask


def detect_contacts(human: HumanMotion, cfg: ContactConfig) -> np.ndarray:
    """(T, 2) bool, (left, right)."""
    out = np.zeros((human.num_frames, 2), dtype=bool)
    still_frames = max(int(round(STILL_S * human.fps)), cfg.min_frames)
    for side, (ankle, toe) in enumerate(FEET):
        pts = human.joint_pos[:, [human.joint_index(ankle), human.joint_index(toe)]]
        height = pts[:, :, 2].min(axis=1)
        # Both ankle and toe slow: a flat stance. Toe-off (heel rising) is left to the free targets.
        speed = np.linalg.norm(np.gradient(pts, 1.0 / human.fps, axis=0), axis=-1).max(axis=1)
        slow = speed < cfg.speed_threshold
        low = height < cfg.height_threshold
        supported = slow & low
        for a, b in runs(slow):
            if b - a >= still_frames:
                supported[a:b] = True
        out[:, side] = _clean(supported, cfg.min_frames)
    return out


def interpolate_over_gaps(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Linear interpolation of (T, ...) values from the frames where `known`; held at the ends."""
    t = np.arange(values.shape[0])
    if not known.any():
        return np.zeros_like(values)
    flat = values.reshape(values.shape[0], -1)
    out = np.stack([np.interp(t, t[known], flat[known, i]) for i in range(flat.shape[1])], axis=1)
    return out.reshape(values.shape)


@dataclass
class FootPins:
    contacts: np.ndarray  # (T, 2) bool
    support_z: np.ndarray  # (T, 2) height of the support under each foot (valid in contact)
    ankle_pos: np.ndarray  # (T, 2, 3) corrected ankle targets (pinned in contact)
    ankle_quat: np.ndarray  # (T, 2, 4) corrected ankle orientations (flat, pinned yaw in contact)
    alpha: np.ndarray  # (T, 2) 1 in contact, ramping to 0 over RAMP_FRAMES around it (weights blend)


def support_elevation(human: HumanMotion, contacts: np.ndarray, cfg: ContactConfig) -> np.ndarray:
    """(T, 2) human support height per contact run (0 on the floor), elsewhere 0."""
    elev = np.zeros(contacts.shape)
    for side, (ankle, toe) in enumerate(FEET):
        pts = human.joint_pos[:, [human.joint_index(ankle), human.joint_index(toe)]]
        height = pts[:, :, 2].min(axis=1)
        for a, b in runs(contacts[:, side]):
            level = float(np.median(height[a:b])) - _floor_level(human)
            # On the floor means exactly on the floor: no centimetres of float from drift or noise.
            elev[a:b, side] = 0.0 if level < cfg.floor_snap else level
    return elev


def _floor_level(human: HumanMotion) -> float:
    feet = [human.joint_index(n) for pair in FEET for n in pair]
    return float(np.percentile(human.joint_pos[:, feet, 2].min(axis=1), 1))


def ground_and_pin(pos: np.ndarray, rot: np.ndarray, names: tuple[str, ...], contacts: np.ndarray,
                   elevation: np.ndarray, scale: float, ankle_height: float) -> tuple[np.ndarray, FootPins]:
    """Shifts all targets vertically so contact feet stand on their support, then pins the feet.

    Returns the shifted keypoint targets (T, K, 3) and the foot pins.
    """
    k = {n: i for i, n in enumerate(names)}
    ankles = [k["left_ankle"], k["right_ankle"]]
    support_z = scale * elevation
    want_z = support_z + ankle_height
    # Whole-body vertical offset: zero float / penetration of the contact feet, interpolated over
    # flight so the (scaled) jump height survives.
    offset = np.zeros(pos.shape[0])
    any_contact = contacts.any(axis=1)
    diff = want_z - pos[:, ankles, 2]
    offset[any_contact] = np.array([diff[t, contacts[t]].mean() for t in np.flatnonzero(any_contact)])
    offset = interpolate_over_gaps(offset, any_contact)
    pos = pos.copy()
    pos[:, :, 2] += offset[:, None]

    n = pos.shape[0]
    ankle_pos = pos[:, ankles].copy()
    ankle_quat = rot[:, ankles].copy()
    alpha = np.zeros((n, 2))
    for side in range(2):
        corr = np.zeros((n, 3))
        for a, b in runs(contacts[:, side]):
            pin = np.array([*pos[a:b, ankles[side], :2].mean(axis=0), want_z[a, side]])
            corr[a:b] = pin - pos[a:b, ankles[side]]
            heading = quat.yaw(rot[a:b, ankles[side]])
            flat = quat.from_yaw(np.array(np.arctan2(np.sin(heading).mean(), np.cos(heading).mean())))
            # Flat and pinned in contact; eased in and out so the ankle does not snap.
            lo, hi = max(0, a - RAMP_FRAMES), min(n, b + RAMP_FRAMES)
            t = np.arange(lo, hi)
            dist = np.maximum(np.maximum(a - t, t - (b - 1)), 0)
            w = 1.0 - dist / (RAMP_FRAMES + 1)
            take = w > alpha[lo:hi, side]
            alpha[lo:hi, side] = np.maximum(alpha[lo:hi, side], w)
            blended = quat.slerp(rot[lo:hi, ankles[side]], np.broadcast_to(flat, (hi - lo, 4)), w)
            ankle_quat[lo:hi, side][take] = blended[take]
        ankle_pos[:, side] += interpolate_over_gaps(corr, contacts[:, side])
    return pos, FootPins(contacts=contacts, support_z=support_z, ankle_pos=ankle_pos, ankle_quat=ankle_quat,
                         alpha=alpha)
