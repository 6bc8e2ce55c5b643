"""`RetargetConfig`: the `retarget:` section of params.yaml as a typed, validated dataclass.

The task table is GMR-style: one row per tracked G1 frame (a `track_<name>` site, see
robots/g1/robot.yaml) naming the SMPL joint it follows and its position / orientation weights.
A weight of 0 drops that half of the task; a frame left out of the table is not tracked.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from pipeline.common.errors import PipelineInputError
from pipeline.human.motion import SMPL_JOINT_NAMES

SOLVERS = ("mink", "placo")
SCALE_MODES = ("height", "fixed")
TIME_SCALES = ("none", "froude")


@dataclass(frozen=True)
class FrameTaskSpec:
    human_joint: str  # SMPL joint whose motion this robot frame follows
    position_weight: float
    orientation_weight: float


# Robot frame -> (SMPL joint, position weight, orientation weight). Orientation is only asked of
# frames whose SMPL frame is well defined and whose robot counterpart can follow it: the trunk and
# the feet (a flat foot on the floor is what keeps contacts clean). Arms follow by position only,
# their rest poses differ too much (T-pose vs arms down) for orientation targets to help.
DEFAULT_TASK_TABLE: dict[str, FrameTaskSpec] = {
    "pelvis": FrameTaskSpec("pelvis", 10.0, 5.0),
    "torso": FrameTaskSpec("spine1", 5.0, 2.0),
    "left_hip": FrameTaskSpec("left_hip", 5.0, 0.0),
    "right_hip": FrameTaskSpec("right_hip", 5.0, 0.0),
    "left_knee": FrameTaskSpec("left_knee", 5.0, 0.0),
    "right_knee": FrameTaskSpec("right_knee", 5.0, 0.0),
    "left_ankle": FrameTaskSpec("left_ankle", 10.0, 3.0),
    "right_ankle": FrameTaskSpec("right_ankle", 10.0, 3.0),
    "head": FrameTaskSpec("head", 2.0, 0.0),
    "left_collar": FrameTaskSpec("left_collar", 2.0, 0.0),
    "right_collar": FrameTaskSpec("right_collar", 2.0, 0.0),
    "left_shoulder": FrameTaskSpec("left_shoulder", 3.0, 0.0),
    "right_shoulder": FrameTaskSpec("right_shoulder", 3.0, 0.0),
    "left_elbow": FrameTaskSpec("left_elbow", 3.0, 0.0),
    "right_elbow": FrameTaskSpec("right_elbow", 3.0, 0.0),
    "left_wrist": FrameTaskSpec("left_wrist", 3.0, 0.0),
    "right_wrist": FrameTaskSpec("right_wrist", 3.0, 0.0),
}


@dataclass(frozen=True)
class ContactConfig:
    """Foot contact from the human clip: low and slow. Heights are above the clip's floor."""

    height_threshold: float = 0.06  # m, foot joint (toe base) height above the floor
    speed_threshold: float = 0.6  # m/s, foot joint speed
    min_frames: int = 3  # shorter contact runs are noise and are dropped
    # A stance whose human support is less than this above the clip's floor is put on the floor
    # (estimated clips drift by several cm); higher ones are steps/boxes and keep their scaled height.
    floor_snap: float = 0.1
    # Weight of the pinned foot position during contact, above the table's ankle weight,
    # so the IK prefers a still foot over the pelvis target when the two disagree.
    pin_weight: float = 50.0


@dataclass(frozen=True)
class RetargetConfig:
    solver: str = "mink"
    qp_solver: str = "daqp"  # qpsolvers backend used by mink
    task_table: dict[str, FrameTaskSpec] = field(default_factory=lambda: dict(DEFAULT_TASK_TABLE))
    posture_weight: float = 0.05  # pulls joints towards the robot's default pose (regularisation)
    damping: float = 0.01  # Levenberg-Marquardt damping of the IK step
    iterations: int = 3  # IK iterations per frame, warm-started from the previous frame
    first_frame_iterations: int = 60  # the first frame starts from the default pose
    velocity_limit_scale: float = 1.0  # fraction of the motors' velocity limits the IK may use
    # The robot's trunk is rigid from pelvis to chest (waist roll/pitch locked): its orientation
    # target is a blend of the human pelvis (0) and chest (1) orientations.
    trunk_blend: float = 0.5
    scale_mode: str = "height"  # "height": robot_height / human.height; "fixed": fixed_scale
    robot_height: float = 1.32  # m, standing height of the G1
    fixed_scale: float = 0.75
    # The clip's timing on the robot. "none": the clip's own. "froude": played sqrt(scale) times as long
    # (faster for a smaller robot), the dynamic similarity of a body scaled by `scale` under the same
    # gravity: positions shrink by scale, times by sqrt(scale), so accelerations, a flight's gravity
    # among them, stay the human's. With "none" a flight the person made under 9.81 m/s² falls at
    # scale × 9.81 on the robot (quality.json: jump.gravity_m_s2).
    time_scale: str = "none"
    contact: ContactConfig = field(default_factory=ContactConfig)
    fps_out: float = 50.0

    @staticmethod
    def from_dict(raw: dict | None, where: str = "retarget") -> "RetargetConfig":
        raw = dict(raw or {})
        if not isinstance(raw, dict):
            raise PipelineInputError(where, None, "must be a mapping")
        known = {f.name for f in fields(RetargetConfig)}
        for key in raw:
            if key not in known:
                raise PipelineInputError(where, key, f"unknown key (expected one of {', '.join(sorted(known))})")
        kwargs: dict[str, Any] = {}
        defaults = RetargetConfig()
        for f in fields(RetargetConfig):
            if f.name not in raw:
                continue
            value = raw[f.name]
            if f.name == "task_table":
                kwargs[f.name] = _parse_task_table(value, f"{where}.task_table")
            elif f.name == "contact":
                kwargs[f.name] = _parse_contact(value, f"{where}.contact")
            elif isinstance(getattr(defaults, f.name), str):
                if not isinstance(value, str):
                    raise PipelineInputError(where, f.name, f"must be a string, got {value!r}")
                kwargs[f.name] = value
            elif isinstance(getattr(defaults, f.name), int) and not isinstance(getattr(defaults, f.name), bool):
                if isinstance(value, bool) or not isinstance(value, int):
                    raise PipelineInputError(where, f.name, f"must be an integer, got {value!r}")
                kwargs[f.name] = value
            else:
                kwargs[f.name] = _number(value, where, f.name)
        cfg = RetargetConfig(**kwargs)
        cfg.validate(where)
        return cfg

    def validate(self, where: str = "retarget") -> None:
        def bad(key: str, problem: str) -> None:
            raise PipelineInputError(where, key, problem)

        if self.solver not in SOLVERS:
            bad("solver", f"must be one of {SOLVERS}, got {self.solver!r}")
        if self.scale_mode not in SCALE_MODES:
            bad("scale_mode", f"must be one of {SCALE_MODES}, got {self.scale_mode!r}")
        if self.time_scale not in TIME_SCALES:
            bad("time_scale", f"must be one of {TIME_SCALES}, got {self.time_scale!r}")
        if self.qp_solver not in _available_qp_solvers():
            bad("qp_solver", f"{self.qp_solver!r} is not installed (have {_available_qp_solvers()})")
        for key in ("posture_weight", "damping"):
            if getattr(self, key) < 0:
                bad(key, f"must be >= 0, got {getattr(self, key)}")
        for key in ("iterations", "first_frame_iterations"):
            if getattr(self, key) < 1:
                bad(key, f"must be >= 1, got {getattr(self, key)}")
        for key in ("robot_height", "fixed_scale", "fps_out", "velocity_limit_scale"):
            if getattr(self, key) <= 0:
                bad(key, f"must be > 0, got {getattr(self, key)}")
        if not 0.0 <= self.trunk_blend <= 1.0:
            bad("trunk_blend", f"must be in [0, 1], got {self.trunk_blend}")
        if not self.task_table:
            bad("task_table", "must track at least one frame")
        if "pelvis" not in self.task_table:
            bad("task_table", "must contain the pelvis (the root of the scaled skeleton)")

    def to_dict(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["task_table"] = {
            k: {"human_joint": v.human_joint, "position_weight": v.position_weight,
                "orientation_weight": v.orientation_weight}
            for k, v in self.task_table.items()
        }
        out["contact"] = {f.name: getattr(self.contact, f.name) for f in fields(ContactConfig)}
        return out


def _available_qp_solvers() -> list[str]:
    import qpsolvers

    return list(qpsolvers.available_solvers)


def _number(value, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise PipelineInputError(where, key, f"must be a number, got {value!r}")
    return float(value)


def _parse_contact(raw, where: str) -> ContactConfig:
    if not isinstance(raw, dict):
        raise PipelineInputError(where, None, "must be a mapping")
    known = {f.name for f in fields(ContactConfig)}
    kwargs: dict[str, Any] = {}
    for key, value in raw.items():
        if key not in known:
            raise PipelineInputError(where, key, f"unknown key (expected one of {', '.join(sorted(known))})")
        if key == "min_frames":
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise PipelineInputError(where, key, f"must be an integer >= 1, got {value!r}")
            kwargs[key] = value
        else:
            number = _number(value, where, key)
            if number <= 0:
                raise PipelineInputError(where, key, f"must be > 0, got {value!r}")
            kwargs[key] = number
    return ContactConfig(**kwargs)


def _parse_task_table(raw, where: str) -> dict[str, FrameTaskSpec]:
    from pipeline.robot.g1 import load_robot_config

    if not isinstance(raw, dict):
        raise PipelineInputError(where, None, "must be a mapping of robot frame -> task")
    frames = load_robot_config().tracked_body_names
    table: dict[str, FrameTaskSpec] = {}
    for frame, row in raw.items():
        if frame not in frames:
            raise PipelineInputError(where, str(frame), f"not a tracked G1 frame (one of {', '.join(frames)})")
        key = f"{where}.{frame}"
        if not isinstance(row, dict):
            raise PipelineInputError(key, None, "must be a mapping with human_joint, position_weight, orientation_weight")
        unknown = sorted(set(row) - {"human_joint", "position_weight", "orientation_weight"})
        if unknown:
            raise PipelineInputError(key, unknown[0], "unknown key (expected human_joint, position_weight, orientation_weight)")
        for need in ("human_joint", "position_weight", "orientation_weight"):
            if need not in row:
                raise PipelineInputError(key, need, "missing")
        if row["human_joint"] not in SMPL_JOINT_NAMES:
            raise PipelineInputError(key, "human_joint", f"{row['human_joint']!r} is not an SMPL body joint")
        pos_w = _number(row["position_weight"], key, "position_weight")
        ori_w = _number(row["orientation_weight"], key, "orientation_weight")
        if pos_w < 0 or ori_w < 0:
            raise PipelineInputError(key, "position_weight" if pos_w < 0 else "orientation_weight", "must be >= 0")
        table[frame] = FrameTaskSpec(row["human_joint"], pos_w, ori_w)
    return table
