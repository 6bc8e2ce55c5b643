"""The deployed policy's metadata: everything a deployment loop needs besides the ONNX graph.

JSON-ready dict, written inside the ONNX (metadata_props) and beside it (policy.json):
robot (joint names/order, PD gains, default pose, action scale, control rate), the observation
layout (terms in order, their sizes, offsets and scales, history length and order), the task
(name, ψ ranges, phase rate and its adapter bounds), keyframes (phases, targets and their
ψ-dependent offsets on a grid), the start pose, terminations, the reference the fall checks
compare against, and the terrain on the ψ grid.

Fall checks (the contract sim2sim implements, the same as `TrackingEnv`): the reference frame of
a phase φ is `round(φ·(T − 1))` clamped to [0, T − 1] (`reference.frame_of_phase`). With
`terminations.relative_to_reference` an episode ends when
  tilt:   |g_xy − reference.projected_gravity_xy[frame]| > max_tilt
  height: z < min(min_base_height, reference.root_height[frame] + z_offset(ψ, frame) − base_height_margin)
          (only where `terminations.base_height_applies`); z_offset interpolates
          `reference.root_height_offset` (G, T) linearly on `reference.psi_grid`,
and otherwise on the absolute values |g_xy| > max_tilt, z < min_base_height. g is the gravity
direction (0, 0, −1) in the pelvis frame, z the pelvis world height.

Observation layout convention (the contract sim2sim implements): one step's observation is the
concatenation of `terms` in order, each `(value - offset) * scale`; the policy input is the
concatenation of the last `history` steps, oldest first, the history filled with the first
step's observation at reset.
"""

from __future__ import annotations

from typing import Callable

import mujoco
import numpy as np

from pipeline.envs.falls import SUCCESS_THRESHOLD_M
from pipeline.envs.feedforward import zero_action_targets
from pipeline.keyframes.tracking_data import TrackingData
from pipeline.robot.g1 import RobotConfig

METADATA_VERSION = 2  # 2: reference arrays + relative fall-check settings
PSI_GRID_POINTS = 41


def default_observation_terms(cfg: RobotConfig) -> list[dict]:
    """The actor observation of the tracking environment (issue 5 / paper), one step."""
    j = cfg.num_joints
    return [
        {"name": "base_ang_vel", "dim": 3, "scale": 1.0},  # pelvis frame, rad/s
        {"name": "projected_gravity", "dim": 3, "scale": 1.0},  # unit gravity in the pelvis frame
        {"name": "joint_pos", "dim": j, "scale": 1.0, "offset": cfg.default_joint_pos.tolist()},
        {"name": "joint_vel", "dim": j, "scale": 1.0},
        {"name": "last_action", "dim": j, "scale": 1.0},  # raw policy action a
        {"name": "phase", "dim": 1, "scale": 1.0},
        {"name": "psi", "dim": 1, "scale": 1.0},
        {"name": "odometry", "dim": 3, "scale": 1.0, "rate_hz": 10.0},  # start-frame position
    ]


def observation_layout(cfg: RobotConfig, history: int = 5, terms: list[dict] | None = None) -> dict:
    terms = terms if terms is not None else default_observation_terms(cfg)
    step_dim = int(sum(t["dim"] for t in terms))
    return {"terms": terms, "step_dim": step_dim, "history": int(history),
            "history_order": "oldest_first", "dim": step_dim * int(history)}


def _grid(data: TrackingData, points: int) -> np.ndarray:
    return np.linspace(float(data.psi.min()), float(data.psi.max()), points) if data.num_samples > 1 \
        else np.array([float(data.psi[0])])


def samples_on_grid(psi: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Per-sample values (S, ...) at each grid ψ (G, ...): linear interpolation between the
    samples sorted by ψ (samples sharing a ψ are averaged), constant beyond the ends."""
    psi, values = np.asarray(psi, dtype=np.float64), np.asarray(values, dtype=np.float64)
    unique, inverse = np.unique(psi, return_inverse=True)
    summed = np.zeros((len(unique),) + values.shape[1:])
    np.add.at(summed, inverse, values)
    mean = (summed.reshape(len(unique), -1) / np.bincount(inverse)[:, None])
    out = np.stack([np.interp(grid, unique, column) for column in mean.T], axis=-1)
    return out.reshape((len(grid),) + values.shape[1:])


def keyframe_offsets_on_grid(data: TrackingData, grid: np.ndarray) -> np.ndarray:
    """(G, K, 3) keyframe offsets at each grid ψ (see `samples_on_grid`)."""
    return samples_on_grid(data.psi, data.keyframe_offsets, grid)


def projected_gravity_xy(quat_wxyz: np.ndarray) -> np.ndarray:
    """(T, 2) x, y of the world gravity direction (0, 0, −1) in the frame of each quaternion
    (the env's `torch_math.projected_gravity`)."""
    w, x, y, z = np.moveaxis(np.asarray(quat_wxyz, dtype=np.float64), -1, 0)
    return np.stack([2.0 * (w * y - x * z), -2.0 * (y * z + w * x)], axis=-1)


def reference_metadata(data: TrackingData, grid: np.ndarray) -> dict:
    """What the reference-relative fall checks read per frame: the root's projected-gravity xy
    and height of the unedited reference, and the ψ edit's z offset of the root at every frame
    on the ψ grid (D_edit: the latest keyframe's offset, D_rule: the dense offset) — the env's
    `offset_table[..., 2]`, interpolated in ψ like the keyframe offsets."""
    motion = data.motion
    t, s = motion.num_frames, data.num_samples
    frames, samples = np.tile(np.arange(t), s), np.repeat(np.arange(s), t)
    z_offsets = np.asarray(data.offsets_at_frames(samples, frames))[:, 2].reshape(s, t)
    return {
        "num_frames": int(t),
        "frame_of_phase": "round(phase * (num_frames - 1)), clamped to [0, num_frames - 1]",
        "root_height": motion.root_pos[:, 2].tolist(),  # (T,) m
        "projected_gravity_xy": projected_gravity_xy(motion.root_quat).tolist(),  # (T, 2)
        "psi_grid": grid.tolist(),
        "root_height_offset": samples_on_grid(data.psi, z_offsets, grid).tolist(),  # (G, T) m
        # the unedited reference pose per frame, for drawing it beside the robot (render/reference.py)
        "root_pos": motion.root_pos.tolist(),  # (T, 3) m
        "root_quat": motion.root_quat.tolist(),  # (T, 4) wxyz
        "joint_pos": motion.joint_pos.tolist(),  # (T, J) in joint_names' order
    }


def termination_metadata(terminations=None, task: str | None = None) -> dict:
    """The env's fall checks (`pipeline.envs.config.TerminationConfig`, its defaults when None)
    for `task`. No keyframe-error limit: evaluation (whose success rate sim2sim reproduces) runs
    without that termination."""
    if terminations is None:
        from pipeline.envs.config import TerminationConfig

        terminations = TerminationConfig()
    applies = bool(terminations.base_height_enabled) and task not in terminations.base_height_exempt_tasks
    return {"max_tilt": float(terminations.max_tilt),
            "min_base_height": float(terminations.min_base_height),
            "base_height_margin": float(terminations.base_height_margin),
            "relative_to_reference": bool(terminations.relative_to_reference),
            "base_height_applies": applies,
            "keyframe_body_error_m": None}


def terrain_geoms(model: mujoco.MjModel) -> list[dict]:
    """World-body geoms of a compiled scene (the ground and task terrain), JSON-ready."""
    out = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != 0:
            continue
        out.append({
            "name": model.geom(g).name,
            "type": int(model.geom_type[g]),
            "size": model.geom_size[g].tolist(),
            "pos": model.geom_pos[g].tolist(),
            "quat": model.geom_quat[g].tolist(),
            "friction": model.geom_friction[g].tolist(),
            "rgba": model.geom_rgba[g].tolist(),
        })
    return out


def terrain_metadata(terrain_builder: Callable | None, layout: Callable[[float], dict] | None,
                     grid: np.ndarray) -> dict:
    """The terrain geoms and, per grid ψ, the moved/resized ones: {name: (pos, size)}."""
    from pipeline.robot.g1 import build_model

    geoms = terrain_geoms(build_model(terrain=terrain_builder, visual=False))
    per_psi = []
    if layout is not None:
        for psi in grid:
            per_psi.append({name: {"pos": list(map(float, p)), "size": list(map(float, s))}
                            for name, (p, s) in layout(float(psi)).items()})
    return {"geoms": geoms, "psi_grid": grid.tolist(), "layouts": per_psi}


def build_metadata(*, task: str, variant: str, robot: RobotConfig, data: TrackingData,
                   obs_layout: dict, terminations: dict | None = None,
                   terrain: dict | None = None, psi_grid_points: int = PSI_GRID_POINTS,
                   action_offset: str = "default") -> dict:
    """`action_offset`: what the policy's joint action is added to (`EnvConfig.action_offset`);
    "reference" and "feedforward" add that offset's per-frame joint targets (`reference.joint_target`,
    envs/feedforward.py) to the recorded formula, and the data's push prior its w(ψ) · push
    (`reference.push_prior`)."""
    motion = data.motion
    grid = _grid(data, psi_grid_points)
    frames = np.asarray(data.keyframe_frames, dtype=int)
    duration = motion.duration
    phase_rate = robot.control_dt / duration
    start = motion.qpos()[0]
    qvel0 = motion.qvel()[0]
    reference = reference_metadata(data, grid)
    joint_targets = "default_joint_pos + action_scale * action"
    if action_offset != "default":
        joint_targets = ("reference.joint_target[frame_of_phase(phase + rate + clamp(phase_rate_offset))]"
                         " + action_scale * action")
        # (T, J), for reading; the graph holds it
        reference["joint_target"] = zero_action_targets(motion, action_offset, robot).tolist()
        prior = getattr(data, "push_prior", None)
        if prior is not None:  # priors/push_prior.py; the graph holds it too
            joint_targets = joint_targets.replace(" + action_scale", " + interp(psi, reference.push_prior.psi_anchors, "
                                                  "reference.push_prior.weight_anchors) * reference.push_prior."
                                                  "joint_offset[frame_of_phase(...)] + action_scale")
            reference["push_prior"] = {"joint_offset": np.asarray(prior.joint_offsets).tolist(),
                                       "psi_anchors": np.asarray(prior.psi_anchors).tolist(),
                                       "weight_anchors": np.asarray(prior.weight_anchors).tolist()}
    return {
        "metadata_version": METADATA_VERSION,
        "task": task,
        "variant": variant,
        **robot.metadata(),
        "control_rate_hz": 1.0 / robot.control_dt,
        "tracked_body_names": list(motion.body_names),
        "tracked_site_names": list(robot.tracked_site_names),
        "observation": obs_layout,
        "action_offset": action_offset,
        "outputs": {"joint_targets": joint_targets,
                    "action": "raw action a (next step's last_action)",
                    "phase_rate_offset": "Δφ^Δ added to the phase rate, clamp [-0.75, +1]·phase_rate"},
        "phase": {"duration_s": duration, "rate": phase_rate,
                  "offset_bounds": [-0.75 * phase_rate, phase_rate], "num_frames": motion.num_frames},
        "psi_ranges": {k: [list(map(float, r)) for r in v] for k, v in data.psi_ranges.items()},
        "psi_raw": float(data.psi_raw),
        "psi_limits": [float(data.psi.min()), float(data.psi.max())],
        "keyframes": {
            "frames": frames.tolist(),
            "phases": (frames / (motion.num_frames - 1)).tolist(),
            "labels": list(data.keyframe_labels),
            "body_pos": motion.body_pos[frames].tolist(),  # (K, B, 3) unedited targets
            "psi_grid": grid.tolist(),
            "offsets": keyframe_offsets_on_grid(data, grid).tolist(),  # (G, K, 3)
        },
        "initial_state": {"qpos": start.tolist(), "qvel": qvel0.tolist()},
        "terminations": terminations or termination_metadata(task=task),
        "reference": reference,
        "success_threshold_m": SUCCESS_THRESHOLD_M,
        "terrain": terrain or {"geoms": [], "psi_grid": [], "layouts": []},
    }
