"""The deployed policy's metadata: everything a deployment loop needs besides the ONNX graph.

JSON-ready dict, written inside the ONNX (metadata_props) and beside it (policy.json):
robot (joint names/order, PD gains, default pose, action scale, control rate), the observation
layout (terms in order, their sizes, offsets and scales, history length and order), the task
(name, ψ ranges, phase rate and its adapter bounds), keyframes (phases, targets and their
ψ-dependent offsets on a grid), the start pose, terminations, and the terrain on the ψ grid.

Observation layout convention (the contract sim2sim implements): one step's observation is the
concatenation of `terms` in order, each `(value - offset) * scale`; the policy input is the
concatenation of the last `history` steps, oldest first, the history filled with the first
step's observation at reset.
"""

from __future__ import annotations

from typing import Callable

import mujoco
import numpy as np

from pipeline.keyframes.tracking_data import TrackingData
from pipeline.robot.g1 import RobotConfig

METADATA_VERSION = 1
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


def keyframe_offsets_on_grid(data: TrackingData, grid: np.ndarray) -> np.ndarray:
    """(G, K, 3) keyframe offsets at each grid ψ: linear interpolation between the samples
    (sorted by ψ; samples sharing a ψ are averaged)."""
    order = np.argsort(data.psi)
    psi, offsets = data.psi[order], data.keyframe_offsets[order]
    unique, inverse = np.unique(psi, return_inverse=True)
    summed = np.zeros((len(unique),) + offsets.shape[1:])
    np.add.at(summed, inverse, offsets)
    mean = summed / np.bincount(inverse)[:, None, None]
    out = np.empty((len(grid),) + offsets.shape[1:])
    for k in range(offsets.shape[1]):
        for axis in range(3):
            out[:, k, axis] = np.interp(grid, unique, mean[:, k, axis])
    return out


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
                   terrain: dict | None = None, psi_grid_points: int = PSI_GRID_POINTS) -> dict:
    motion = data.motion
    grid = _grid(data, psi_grid_points)
    frames = np.asarray(data.keyframe_frames, dtype=int)
    duration = motion.duration
    phase_rate = robot.control_dt / duration
    start = motion.qpos()[0]
    qvel0 = motion.qvel()[0]
    return {
        "metadata_version": METADATA_VERSION,
        "task": task,
        "variant": variant,
        **robot.metadata(),
        "control_rate_hz": 1.0 / robot.control_dt,
        "tracked_body_names": list(motion.body_names),
        "tracked_site_names": list(robot.tracked_site_names),
        "observation": obs_layout,
        "outputs": {"joint_targets": "default_joint_pos + action_scale * action",
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
        "terminations": terminations or {"max_tilt": 0.8, "min_base_height": 0.4,
                                         "keyframe_body_error_m": None},
        "success_threshold_m": 1.0,
        "terrain": terrain or {"geoms": [], "psi_grid": [], "layouts": []},
    }
