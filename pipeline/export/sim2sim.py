"""Sim2sim: a deployment-style single-robot MuJoCo loop on the exported policy alone.

Uses only `policy.onnx`, `policy.json` and mujoco + numpy + onnxruntime — no training code, no
torch — like a script on the robot's computer: it builds each observation itself from the
metadata's layout, applies the joint targets through the PD actuators, advances the phase with
the policy's Δφ^Δ and scores the episode with the evaluation's success definition (mean tracked-
body world error ≤ 1 m at every keyframe, every keyframe reached). The scene is the G1 model from
`pipeline.robot` (the vendored MJCF) with the gains and terrain taken from the metadata.
Episodes end like the evaluation's (`FallCheck`): falls judged against the reference at the
current frame, from the metadata's `reference` arrays, so its success rate reproduces it.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import mujoco
import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.envs.falls import SUCCESS_THRESHOLD_M, fall_flags
from pipeline.export.policy_step import METADATA_NAME, PolicyStepper, projected_gravity, rotate_z, yaw_of

ONNX_NAME = "policy.onnx"


class PsiOutOfRangeWarning(UserWarning):
    """ψ outside the range the policy was trained on: it still runs, results are extrapolation."""


# ------------------------------------------------------------------------------ loading
def load_exported(policy_dir: str | Path, *, task: str | None = None, robot: str | None = None):
    """(onnxruntime session, metadata) of an exported folder, checked against `task` / `robot`."""
    import onnxruntime as ort

    policy_dir = Path(policy_dir)
    onnx_path, meta_path = policy_dir / ONNX_NAME, policy_dir / METADATA_NAME
    if not policy_dir.is_dir():
        raise PipelineInputError(policy_dir, None, "exported policy folder not found (run the export stage)")
    if not onnx_path.is_file():
        raise PipelineInputError(onnx_path, None, "ONNX policy file not found (run the export stage)")
    if not meta_path.is_file():
        raise PipelineInputError(meta_path, None, "policy metadata json not found beside the ONNX file")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as error:
        raise PipelineInputError(meta_path, None, f"not valid JSON ({error})") from None
    task_keys = ("keyframes",) if meta.get("kind") != "balance" else ()  # a balance policy has no keyframes
    for key in ("robot", "task", "joint_names", "observation", "phase", *task_keys):
        if key not in meta:
            raise PipelineInputError(meta_path, key, "missing from the policy metadata")
    if task is not None and meta["task"] != task:
        raise PipelineInputError(meta_path, "task", f"policy was trained for task {meta['task']!r}, not {task!r}")
    if robot is not None and meta["robot"] != robot:
        raise PipelineInputError(meta_path, "robot", f"policy is for robot {meta['robot']!r}, not {robot!r}")
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    try:
        session = ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])
    except Exception as error:  # onnxruntime raises its own types for corrupt files
        raise PipelineInputError(onnx_path, None, f"cannot be loaded by onnxruntime ({error})") from None
    expected = meta["observation"]["dim"]
    got = session.get_inputs()[0].shape[-1]
    if isinstance(got, int) and got != expected:
        raise PipelineInputError(onnx_path, "obs", f"ONNX input has {got} values, metadata layout says {expected}")
    return session, meta


def check_psi(meta: dict, psi: float, source: str = "psi") -> bool:
    """Warns (does not fail) when ψ is outside the trained range; True when inside."""
    lo, hi = meta.get("psi_limits", [-np.inf, np.inf])
    if not lo - 1e-9 <= psi <= hi + 1e-9:
        warnings.warn(f"{source}: ψ = {psi:g} is outside the trained range [{lo:g}, {hi:g}] of task "
                      f"{meta.get('task')!r}; running anyway (extrapolation)", PsiOutOfRangeWarning, stacklevel=2)
        return False
    return True


def _interp_grid(grid: list[float], values: np.ndarray, psi: float) -> np.ndarray:
    """Linear interpolation of values (G, ...) on the ψ grid, clamped at its ends."""
    grid = np.asarray(grid, dtype=np.float64)
    if len(grid) == 1:
        return values[0]
    i = int(np.clip(np.searchsorted(grid, psi) - 1, 0, len(grid) - 2))
    a = float(np.clip((psi - grid[i]) / (grid[i + 1] - grid[i]), 0.0, 1.0))
    return (1 - a) * values[i] + a * values[i + 1]


# ------------------------------------------------------------------------------ the scene
def terrain_layout_at(meta: dict, psi: float) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{geom name: (pos, size)} of the terrain at ψ: linear between the two nearest grid layouts."""
    terrain = meta.get("terrain") or {}
    layouts = terrain.get("layouts") or []
    if not layouts:
        return {}
    grid = np.asarray(terrain["psi_grid"])
    i = int(np.argmin(np.abs(grid - psi)))
    return {name: (_interp_grid(grid, np.array([l[name]["pos"] for l in layouts]), psi),
                   _interp_grid(grid, np.array([l[name]["size"] for l in layouts]), psi)) for name in layouts[i]}


def _terrain_adder(meta: dict, psi: float) -> Callable[[mujoco.MjSpec], None]:
    geoms = (meta.get("terrain") or {}).get("geoms") or []
    layout = terrain_layout_at(meta, psi)

    def add(spec: mujoco.MjSpec) -> None:
        if not geoms:
            from pipeline.robot.g1 import add_flat_ground

            add_flat_ground(spec)
            return
        for g in geoms:
            pos, size = layout.get(g["name"], (g["pos"], g["size"]))
            spec.worldbody.add_geom(name=g["name"] or "", type=mujoco.mjtGeom(g["type"]), size=list(size),
                                    pos=list(pos), quat=g["quat"], friction=g["friction"], rgba=g["rgba"],
                                    contype=1, conaffinity=1, condim=3)

    return add


def build_scene(meta: dict, psi: float, visual: bool = False) -> mujoco.MjModel:
    """The G1 scene at this ψ, actuator gains set from the metadata (what the robot would run)."""
    from pipeline.robot.g1 import build_spec, load_robot_config

    # Exports older than the physics presets name none: the robot's default preset
    physics = load_robot_config().physics(meta.get("physics"), source="policy.json", field_name="physics")
    spec = build_spec(terrain=_terrain_adder(meta, psi), visual=visual, physics=physics)
    if visual:
        spec.visual.quality.offsamples = 0  # multisampling costs more than it shows at 640x480
    model = spec.compile()
    kp, kd = np.asarray(meta["kp"]), np.asarray(meta["kd"])
    for j, name in enumerate(meta["joint_names"]):
        act = model.actuator(name).id
        model.actuator_gainprm[act, 0] = kp[j]
        model.actuator_biasprm[act, 1:3] = [-kp[j], -kd[j]]
    return model


# ------------------------------------------------------------------------------ falls
def reference_frame(phase: float, num_frames: int) -> int:
    """The reference frame of a phase, as the env maps it (round half to even, like torch)."""
    return int(np.clip(np.rint(phase * (num_frames - 1)), 0, num_frames - 1))


@dataclass(frozen=True)
class FallCheck:
    """The env's fall terminations for one episode at one ψ (see `pipeline.export.metadata`).

    Relative (the reference arrays given): tilt |g_xy − g_xy,ref[frame]| > max_tilt, height
    z < min(min_base_height, z_ref[frame] − base_height_margin) with z_ref including the ψ edit.
    Absolute (no arrays): |g_xy| > max_tilt, z < min_base_height. `min_base_height` None: no
    height check for this task."""

    max_tilt: float
    min_base_height: float | None
    base_height_margin: float = 0.0
    ref_gravity_xy: np.ndarray | None = None  # (T, 2)
    ref_root_height: np.ndarray | None = None  # (T,) reference pelvis z + the ψ edit's z offset

    @classmethod
    def from_metadata(cls, meta: dict, psi: float) -> "FallCheck":
        term = meta.get("terminations") or {}
        # before metadata version 2 the height check was off where min_base_height was None
        applies = term.get("base_height_applies", term.get("min_base_height") is not None)
        min_height = float(term["min_base_height"]) if applies and term.get("min_base_height") is not None else None
        max_tilt = float(term.get("max_tilt", np.inf))
        ref = meta.get("reference")
        if not term.get("relative_to_reference", False):
            return cls(max_tilt, min_height)
        if not ref:
            raise PipelineInputError(METADATA_NAME, "reference",
                                     "relative fall checks need the reference arrays (re-run the export)")
        offset = _interp_grid(ref["psi_grid"], np.asarray(ref["root_height_offset"], dtype=np.float64), psi)
        return cls(max_tilt, min_height, float(term.get("base_height_margin", 0.0)),
                   np.asarray(ref["projected_gravity_xy"], dtype=np.float64),
                   np.asarray(ref["root_height"], dtype=np.float64) + offset)

    def __call__(self, gravity: np.ndarray, base_height: float, frame: int) -> str | None:
        """Which check ends the episode: "tilt", "height" (tilt first when both fire) or None."""
        tilt_xy = np.asarray(gravity[:2], dtype=np.float64)
        if self.ref_gravity_xy is not None:
            tilt_xy = tilt_xy - self.ref_gravity_xy[frame]
        min_height = self.min_base_height
        if min_height is not None and self.ref_root_height is not None:
            min_height = min(min_height, self.ref_root_height[frame] - self.base_height_margin)
        by_tilt, by_height = fall_flags(tilt_xy, base_height, self.max_tilt, min_height)
        return "tilt" if by_tilt else "height" if by_height else None


# ------------------------------------------------------------------------------ judging
class EpisodeJudge:
    """The evaluation's verdict on one episode, fed step by step with what a simulator measures:
    keyframe errors when the phase passes a keyframe, the fall checks at the current frame."""

    def __init__(self, meta: dict, psi: float, keyframe_targets: np.ndarray):
        self.keyframe_phases = np.asarray(meta["keyframes"]["phases"])
        self.targets = keyframe_targets  # (K, B, 3)
        self.error_limit = (meta.get("terminations") or {}).get("keyframe_body_error_m")
        self.threshold = float(meta.get("success_threshold_m", SUCCESS_THRESHOLD_M))
        self.fall = FallCheck.from_metadata(meta, psi)
        self.num_frames = int(meta["phase"]["num_frames"])
        self.errors: list[float] = []
        self.next_keyframe = 0

    def update(self, phase: float, site_xpos: np.ndarray, gravity: np.ndarray, base_height: float) -> str | None:
        """After a step that reached `phase`: the end reason ("keyframe_error", "tilt", "height",
        "done") or None to go on."""
        end = None
        while (self.next_keyframe < len(self.keyframe_phases)
               and self.keyframe_phases[self.next_keyframe] <= phase + 1e-6):
            err = np.linalg.norm(site_xpos - self.targets[self.next_keyframe], axis=-1)
            self.errors.append(float(err.mean()))
            self.next_keyframe += 1
            if self.error_limit is not None and err.max() > self.error_limit:
                end = "keyframe_error"
        if end is not None:
            return end
        fallen = self.fall(gravity, base_height, reference_frame(phase, self.num_frames))
        if fallen is not None:
            return fallen
        return "done" if phase >= 1.0 - 1e-6 else None

    @property
    def success(self) -> bool:
        # the evaluation's definition: every keyframe reached, none with body-mean error > threshold
        return self.success_through(1.0)

    def success_through(self, phase: float) -> bool:
        """The success test over the keyframes up to `phase` (a chain's handoff: the keyframes after it belong
        to no policy): each reached, none with body-mean error > threshold."""
        due = int(np.sum(self.keyframe_phases <= phase + 1e-6))
        return due > 0 and len(self.errors) >= due and all(e <= self.threshold for e in self.errors[:due])


# ------------------------------------------------------------------------------ observations
@dataclass
class RobotState:
    """What the robot's estimator gives, read from MuJoCo."""

    model: mujoco.MjModel
    data: mujoco.MjData
    joint_qpos: np.ndarray
    joint_qvel: np.ndarray

    def base_ang_vel(self) -> np.ndarray:
        return self.data.qvel[3:6].copy()  # free joint: body-frame angular velocity

    def projected_gravity(self) -> np.ndarray:
        return projected_gravity(self.data.qpos[3:7])

    def joint_pos(self) -> np.ndarray:
        return self.data.qpos[self.joint_qpos].copy()

    def joint_vel(self) -> np.ndarray:
        return self.data.qvel[self.joint_qvel].copy()


# ------------------------------------------------------------------------------ the loop
@dataclass
class EpisodeResult:
    psi: float
    success: bool
    keyframe_errors: list[float]  # body-mean world error (m) at each keyframe reached
    steps: int
    end: str  # "done" (phase reached 1), "tilt", "height", "keyframe_error", "max_steps"
    phase: list[float] = field(default_factory=list)
    phase_rate_offset: list[float] = field(default_factory=list)
    final_base_pos: list[float] = field(default_factory=list)  # world pelvis position at the end


class Sim2Sim:
    def __init__(self, policy_dir: str | Path, *, task: str | None = None, robot: str | None = None):
        self.session, self.meta = load_exported(policy_dir, task=task, robot=robot)
        m = self.meta
        self.stepper = PolicyStepper(self.session, m)
        self.control_dt = self.stepper.control_dt
        self.decimation = int(round(m["control_dt"] / m["sim_dt"]))
        self.default_joint_pos = np.asarray(m["default_joint_pos"])
        self.phase_rate = self.stepper.phase_rate
        kf = m["keyframes"]
        self.keyframe_phases = np.asarray(kf["phases"])
        self.keyframe_body_pos = np.asarray(kf["body_pos"])  # (K, B, 3)
        self.keyframe_grid = kf["psi_grid"]
        self.keyframe_offsets = np.asarray(kf["offsets"])  # (G, K, 3)

    def keyframe_targets(self, psi: float) -> np.ndarray:
        offsets = _interp_grid(self.keyframe_grid, self.keyframe_offsets, psi)  # (K, 3)
        return self.keyframe_body_pos + offsets[:, None, :]

    def run_episode(self, psi: float, *, max_steps: int | None = None,
                    on_step: Callable[[mujoco.MjModel, mujoco.MjData, dict], None] | None = None,
                    visual: bool = False) -> EpisodeResult:
        m = self.meta
        check_psi(m, psi)
        model = build_scene(m, psi, visual=visual)
        data = mujoco.MjData(model)
        state = RobotState(
            model, data,
            np.array([model.jnt_qposadr[model.joint(n).id] for n in m["joint_names"]]),
            np.array([model.jnt_dofadr[model.joint(n).id] for n in m["joint_names"]]),
        )
        actuators = np.array([model.actuator(n).id for n in m["joint_names"]])
        sites = np.array([model.site(n).id for n in m["tracked_site_names"]])
        data.qpos[:] = m["initial_state"]["qpos"]
        data.qvel[:] = m["initial_state"]["qvel"]
        mujoco.mj_forward(model, data)

        targets = self.keyframe_targets(psi)
        judge = EpisodeJudge(m, psi, targets)
        start_pos = data.qpos[0:3].copy()
        start_yaw = yaw_of(data.qpos[3:7])
        phases, offsets = [], []
        limit = max_steps or self.stepper.max_steps
        stepper = self.stepper
        stepper.reset()
        end = "max_steps"
        step = 0
        for step in range(1, limit + 1):
            odometry = rotate_z(data.qpos[0:3] - start_pos, -start_yaw) if stepper.odometry_due() else None
            out = stepper.step(base_ang_vel=state.base_ang_vel(), projected_gravity=state.projected_gravity(),
                               joint_pos=state.joint_pos(), joint_vel=state.joint_vel(), psi=psi,
                               odometry=odometry)
            data.ctrl[actuators] = out.joint_targets
            for _ in range(self.decimation):
                mujoco.mj_step(model, data)
            phases.append(out.phase)
            offsets.append(out.phase_rate_offset)
            verdict = judge.update(out.phase, data.site_xpos[sites], state.projected_gravity(), float(data.qpos[2]))
            if on_step is not None:
                on_step(model, data, {"phase": out.phase, "psi": psi, "keyframe_targets": targets, "step": step})
            if verdict is not None:
                end = verdict
                break
        return EpisodeResult(float(psi), judge.success, judge.errors, step, end, phases, offsets,
                             data.qpos[0:3].tolist())


def run_sim2sim(policy_dir: str | Path, psi_values, *, task: str | None = None,
                robot: str | None = None, max_steps: int | None = None) -> dict:
    """Episodes at the given ψ values; returns the success rate (%) and per-episode results."""
    runner = Sim2Sim(policy_dir, task=task, robot=robot)
    results = [runner.run_episode(float(psi), max_steps=max_steps) for psi in psi_values]
    return {
        "task": runner.meta["task"],
        "variant": runner.meta.get("variant"),
        "success": 100.0 * float(np.mean([r.success for r in results])) if results else float("nan"),
        "episodes": [{"psi": r.psi, "success": r.success, "end": r.end, "steps": r.steps,
                      "keyframe_errors": r.keyframe_errors} for r in results],
    }
