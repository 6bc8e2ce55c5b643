"""`retarget(human, cfg, fps_out=50) -> (Motion, report)`: the retarget stage's logic.

Order: scaled skeleton targets -> contacts, ground and foot pins -> IK at the source rate (warm
start) -> G1 `Motion` via RobotKinematics -> resample to fps_out -> final floor correction on the
output frames (root height only; removes the IK's residual float / penetration of contact feet and
any geom below the floor) -> quality report. Same input and config give the same bytes: the IK is
sequential, the QP solver deterministic, the report holds no timing, and the BLAS kernels are the
same on every x86-64 machine (pipeline/common/cpu_kernels.py).
"""

from __future__ import annotations

import time
from functools import lru_cache

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.human.motion import HumanMotion
from pipeline.motion.feet import detect_foot_contacts, find_flights
from pipeline.motion.motion import Motion, RobotKinematics
from pipeline.retarget import contacts as contact_ops
from pipeline.retarget.config import RetargetConfig
from pipeline.retarget.ik import make_retargeter
from pipeline.retarget.quality import (GeomHeights, balance_report, flights_report, foot_skate, joint_report,
                                       keypoint_error, torque_report)
from pipeline.retarget.skeleton import RobotGeometry, body_scale, transfer_skeleton
from pipeline.robot.g1 import build_model, joint_limits, load_robot_config

MIN_DURATION_S = 1.0


@lru_cache(maxsize=1)
def _robot():
    model = build_model(visual=False)
    kin = RobotKinematics(model)
    geometry = RobotGeometry.from_model(model, kin.body_names, kin.site_index)
    return model, kin, geometry


def retarget(human: HumanMotion, cfg: RetargetConfig | None = None, fps_out: float | None = None,
             progress: bool = True) -> tuple[Motion, dict]:
    cfg = cfg or RetargetConfig()
    fps_out = float(fps_out or cfg.fps_out)
    if human.duration < MIN_DURATION_S:
        raise PipelineInputError(human.source, "frames",
                                 f"clip is {human.duration:.2f} s long, retargeting needs >= {MIN_DURATION_S} s")
    started = time.perf_counter()
    model, kin, geometry = _robot()
    names = kin.body_names
    k = {n: i for i, n in enumerate(names)}

    scale = body_scale(human, cfg.scale_mode, cfg.robot_height, cfg.fixed_scale)
    # The robot's clock: a source frame lasts `duration_scale` times as long as the human's did.
    duration_scale = float(np.sqrt(scale)) if cfg.time_scale == "froude" else 1.0
    fps_src = human.fps / duration_scale
    joint_of = {name: row.human_joint for name, row in cfg.task_table.items()}
    targets = transfer_skeleton(human, geometry, scale, cfg.trunk_blend, joint_of)
    contacts = contact_ops.detect_contacts(human, cfg.contact)
    elevation = contact_ops.support_elevation(human, contacts, cfg.contact)
    target_pos, pins = contact_ops.ground_and_pin(targets.pos, targets.quat, names, contacts, elevation,
                                                  scale, geometry.ankle_height)
    for side, (knee, ankle) in enumerate((("left_knee", "left_ankle"), ("right_knee", "right_ankle"))):
        # The knee takes half the pin's correction, so the leg chain stays consistent with the foot.
        target_pos[:, k[knee]] += 0.5 * (pins.ankle_pos[:, side] - target_pos[:, k[ankle]])
        target_pos[:, k[ankle]] = pins.ankle_pos[:, side]
    target_quat = targets.quat.copy()
    target_quat[:, k["left_ankle"]] = pins.ankle_quat[:, 0]
    target_quat[:, k["right_ankle"]] = pins.ankle_quat[:, 1]

    qpos = _solve(model, cfg, human, names, target_pos, target_quat, pins.alpha, fps_src, progress)
    solve_s = time.perf_counter() - started
    if progress:
        # Printed, not reported: quality.json holds only what the inputs determine, so a rerun
        # writes the same bytes (and dvc.lock the same md5).
        print(f"retarget {human.name}: {human.num_frames} frames solved in {solve_s:.2f} s", flush=True)

    joint_pos = qpos[:, kin.qpos_index]
    limits = joint_limits(model, kin.joint_names)
    joint_pos = np.clip(joint_pos, limits[:, 0], limits[:, 1])  # QP tolerance only (~1e-9)
    source_motion = kin.motion(fps_src, qpos[:, :3], qpos[:, 3:7], joint_pos, name=human.name,
                               source=human.source)
    tracked = [k[n] for n in cfg.task_table if cfg.task_table[n].position_weight > 0]
    kp_err = keypoint_error(source_motion.body_pos, target_pos, k["pelvis"], tracked)
    uniform = np.stack([human.joint_pos[:, human.joint_index(cfg.task_table[n].human_joint)]
                        if n in cfg.task_table else human.joint_pos[:, 0] for n in names], axis=1)
    kp_err_uniform = keypoint_error(source_motion.body_pos, scale * uniform, k["pelvis"], tracked)

    out = source_motion.resample(fps_out)
    out_contacts = _resample_mask(contacts, fps_src, fps_out, out.num_frames)
    out_support = _resample_nearest(pins.support_z, fps_src, fps_out, out.num_frames)
    heights = GeomHeights(model, kin.qpos_index, (model.site_bodyid[kin.site_index[k["left_ankle"]]],
                                                  model.site_bodyid[kin.site_index[k["right_ankle"]]]))
    root_pos = out.root_pos.copy()
    root_pos[:, 2] += _floor_correction(out, heights, out_contacts, out_support)
    out = kin.motion(fps_out, root_pos, out.root_quat, out.joint_pos, name=human.name, source=human.source)

    feet_z, lowest_z = heights.lowest(out)
    ankles = out.body_pos[:, [k["left_ankle"], k["right_ankle"]]]
    skate_mean, skate_max = foot_skate(ankles, out_contacts)
    # The flights: the one detector the keyframe stage uses, on the robot's own reference; the human's are
    # the same moments of the clip, at its frame rate.
    flights = find_flights(detect_foot_contacts(out), fps_out)
    human_flights = [(int(round(a * fps_src / fps_out)), int(round(b * fps_src / fps_out))) for a, b in flights]
    float_mm = [float(np.abs(feet_z[out_contacts[:, s], s] - out_support[out_contacts[:, s], s]).max(initial=0.0))
                for s in range(2)]
    report = {
        "name": human.name,
        "solver": cfg.solver,
        "frames_in": human.num_frames,
        "frames_out": out.num_frames,
        "fps_in": human.fps,
        "fps_out": fps_out,
        "scale": scale,
        "duration_scale": duration_scale,
        "keypoint_err_mm": 1e3 * kp_err,
        "keypoint_err_uniform_mm": 1e3 * kp_err_uniform,
        "foot_skate_mm_per_frame": 1e3 * skate_mean,
        "foot_skate_max_mm_per_frame": 1e3 * skate_max,
        "max_penetration_mm": 1e3 * max(0.0, -float(lowest_z.min())),
        "max_contact_foot_float_mm": 1e3 * max(float_mm),
        "contact_fraction": [float(x) for x in out_contacts.mean(axis=0)],
        **joint_report(out, model),
        "jump": flights_report(out.root_pos, flights, fps_out, com=heights.center_of_mass(out)),
        "balance": balance_report(out, heights, out_contacts),
        "torque": torque_report(out, model, load_robot_config()),
        "human_jump_scaled": flights_report(scale * human.joint_pos[:, 0], human_flights, fps_src,
                                            com=scale * _human_center_of_mass(human)),
    }
    return out, report


def _human_center_of_mass(human: HumanMotion) -> np.ndarray:
    """(T, 3) the person's centre of mass (SMPL segment masses)."""
    from pipeline.human import smpl

    names = smpl.SMPL_JOINT_NAMES
    return smpl.center_of_mass(human.joint_pos[:, [human.joint_index(n) for n in names]])


def _solve(model, cfg: RetargetConfig, human: HumanMotion, names, target_pos, target_quat, pin_alpha,
           fps: float, progress: bool) -> np.ndarray:
    from tqdm import tqdm

    ik = make_retargeter(model, cfg, 1.0 / fps)  # the robot's frame time: the IK's velocity limits
    k = {n: i for i, n in enumerate(names)}
    poses = np.concatenate([target_quat, target_pos], axis=-1)  # (T, K, 7) wxyz_xyz
    qpos = np.zeros((human.num_frames, model.nq))
    feet = (("left_ankle", 0), ("right_ankle", 1))
    table = cfg.task_table
    pin_w = cfg.contact.pin_weight
    frames = tqdm(range(human.num_frames), desc=f"retarget {human.name}", unit="frame",
                  disable=not progress, leave=False)
    for t in frames:
        for name, side in feet:
            if name in table:
                row, a = table[name], pin_alpha[t, side]
                pos_w = row.position_weight + a * max(pin_w - row.position_weight, 0.0)
                ori_w = row.orientation_weight + a * max(0.2 * pin_w - row.orientation_weight, 0.0)
                ik.set_weights(name, pos_w, ori_w)
        frame_targets = {name: poses[t, k[name]] for name in ik.frames}
        first = t == 0
        qpos[t] = ik.solve(frame_targets, cfg.first_frame_iterations if first else cfg.iterations, first=first)
    return qpos


def _resample_mask(mask: np.ndarray, fps_in: float, fps_out: float, n: int) -> np.ndarray:
    """A resampled frame is in contact when both source frames around it are."""
    t = np.arange(n) * fps_in / fps_out
    i0 = np.clip(np.floor(t + 1e-9).astype(int), 0, len(mask) - 1)
    i1 = np.clip(np.ceil(t - 1e-9).astype(int), 0, len(mask) - 1)
    return mask[i0] & mask[i1]


def _resample_nearest(x: np.ndarray, fps_in: float, fps_out: float, n: int) -> np.ndarray:
    idx = np.clip(np.round(np.arange(n) * fps_in / fps_out).astype(int), 0, len(x) - 1)
    return x[idx]


def _floor_correction(motion: Motion, heights: GeomHeights, contacts: np.ndarray, support: np.ndarray) -> np.ndarray:
    """Root z offset (T,): contact feet exactly on their support, interpolated in flight, and
    nothing below z = 0."""
    feet_z, lowest = heights.lowest(motion)
    any_contact = contacts.any(axis=1)
    err = np.zeros(motion.num_frames)
    for t in np.flatnonzero(any_contact):
        err[t] = np.max(support[t, contacts[t]] - feet_z[t, contacts[t]])  # lowest contact foot on its support
    dz = contact_ops.interpolate_over_gaps(err, any_contact)
    return dz + np.maximum(0.0, -(lowest + dz))
