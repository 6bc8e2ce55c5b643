"""Builds the G1 MuJoCo model in code (MjSpec) from the vendored mjlab MJCF and robots/g1/robot.yaml.

What this adds to the upstream MJCF, as AdaMimic uses the robot:
  * waist roll and pitch welded (27 actuated joints);
  * position actuators with the armature-based PD design (Kp = J w^2, Kd = 2 zeta J w) and the
    motors' effort limits, joint armature = J;
  * the 17 tracked bodies as sites `track_<name>`;
  * robot-vs-world collisions only (no self collisions), feet as capsules with condim 3;
  * the ground from a terrain hook (flat plane by default);
  * the physics settings of one named preset of robot.yaml `physics:` (timestep, integrator, friction
    cone, which geoms collide): `baseline`, the reference every figure was measured with, or a cheaper
    one (docs/physics.md).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Callable

import mujoco
import numpy as np
import yaml

from pipeline.common.errors import PipelineInputError
from pipeline.robot.assets import ROBOT_DIR, mjcf_path

TerrainBuilder = Callable[[mujoco.MjSpec], None]
TRACK_SITE_PREFIX = "track_"
ROBOT_YAML = "robots/g1/robot.yaml"

INTEGRATORS = {"implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST, "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
               "euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4}
CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}
# Which robot geoms collide with the world: "all" of its collision geoms, or the "feet" alone (a fallen
# robot then sinks into the ground until a fall check, which reads the base's pose, ends the episode).
COLLISION_SETS = ("all", "feet")
FOOT_CAPSULES = tuple(range(1, 8))  # the MJCF's <side>_foot1..7_collision capsules


@dataclass(frozen=True)
class PhysicsConfig:
    """One physics preset of robot.yaml `physics.presets`. The control rate (control_dt) is the
    robot's and never changes with it: a coarser timestep means fewer substeps per control step."""

    name: str
    timestep: float
    integrator: str = "implicitfast"
    cone: str = "pyramidal"
    collisions: str = "all"
    foot_capsules: tuple[int, ...] = FOOT_CAPSULES

    @classmethod
    def from_dict(cls, name: str, raw, source: str = ROBOT_YAML) -> "PhysicsConfig":
        where = f"physics.presets.{name}"
        if not isinstance(raw, dict):
            raise PipelineInputError(source, where, f"must be a mapping, got {type(raw).__name__}")
        known = {"timestep", "integrator", "cone", "collisions", "foot_capsules"}
        unknown = sorted(set(raw) - known)
        if unknown:
            raise PipelineInputError(source, f"{where}.{unknown[0]}", f"unknown key (known: {', '.join(sorted(known))})")
        if "timestep" not in raw:
            raise PipelineInputError(source, f"{where}.timestep", "missing")
        timestep = raw["timestep"]
        if isinstance(timestep, bool) or not isinstance(timestep, (int, float)) or not 0.0 < timestep <= 0.05:
            raise PipelineInputError(source, f"{where}.timestep", f"must be a number in (0, 0.05] s, got {timestep!r}")
        choices = {"integrator": tuple(INTEGRATORS), "cone": tuple(CONES), "collisions": COLLISION_SETS}
        for key, allowed in choices.items():
            if key in raw and raw[key] not in allowed:
                raise PipelineInputError(source, f"{where}.{key}", f"must be one of {', '.join(allowed)}, got {raw[key]!r}")
        capsules = raw.get("foot_capsules", list(FOOT_CAPSULES))
        if (not isinstance(capsules, list) or not capsules
                or any(isinstance(c, bool) or c not in FOOT_CAPSULES for c in capsules)
                or len(set(capsules)) != len(capsules)):
            raise PipelineInputError(source, f"{where}.foot_capsules",
                                     f"must be a non-empty list of distinct capsule numbers 1..7, got {capsules!r}")
        return cls(name=name, timestep=float(timestep), integrator=raw.get("integrator", "implicitfast"),
                   cone=raw.get("cone", "pyramidal"), collisions=raw.get("collisions", "all"),
                   foot_capsules=tuple(sorted(int(c) for c in capsules)))

    def apply(self, spec: mujoco.MjSpec) -> None:
        """Sets the solver options of `spec` (the geoms' collision flags are set in build_spec)."""
        spec.option.timestep = self.timestep
        spec.option.integrator = INTEGRATORS[self.integrator]
        spec.option.cone = CONES[self.cone]


@dataclass(frozen=True)
class RobotConfig:
    name: str
    joint_names: tuple[str, ...]
    default_joint_pos: np.ndarray
    armature: np.ndarray
    kp: np.ndarray
    kd: np.ndarray
    effort_limit: np.ndarray
    velocity_limit: np.ndarray
    action_scale: np.ndarray
    tracked_bodies: dict[str, tuple[str, tuple[float, float, float]]]
    feet: dict[str, dict]
    locked_joints: tuple[str, ...]
    sim_dt: float
    control_dt: float
    default_root_height: float
    foot_friction: float
    natural_frequency_hz: float = 10.0
    damping_ratio: float = 2.0
    motor_of_joint: dict[str, str] = field(default_factory=dict)
    # robot.yaml `physics`: the named presets and the one used where none is asked for (sim_dt is its timestep)
    physics_presets: dict[str, PhysicsConfig] = field(default_factory=dict)
    default_physics: str = "baseline"

    def physics(self, name: str | None = None, source: str = ROBOT_YAML, field_name: str = "physics") -> PhysicsConfig:
        """The preset `name` (None: the default one); an unknown name is a PipelineInputError
        naming `source` and `field_name`, the file and key the name came from."""
        name = self.default_physics if name is None else name
        if name not in self.physics_presets:
            raise PipelineInputError(source, field_name, f"unknown physics preset {name!r} "
                                     f"(robot.yaml physics.presets: {', '.join(self.physics_presets)})")
        return self.physics_presets[name]

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def decimation(self) -> int:
        return int(round(self.control_dt / self.sim_dt))

    @property
    def tracked_body_names(self) -> tuple[str, ...]:
        return tuple(self.tracked_bodies)

    @property
    def tracked_site_names(self) -> tuple[str, ...]:
        return tuple(TRACK_SITE_PREFIX + name for name in self.tracked_bodies)

    def metadata(self) -> dict:
        """What a deployment needs to know about the robot, JSON-ready."""
        return {
            "robot": self.name,
            "joint_names": list(self.joint_names),
            "default_joint_pos": self.default_joint_pos.tolist(),
            "kp": self.kp.tolist(),
            "kd": self.kd.tolist(),
            "effort_limit": self.effort_limit.tolist(),
            "action_scale": self.action_scale.tolist(),
            "sim_dt": self.sim_dt,
            "control_dt": self.control_dt,
        }


def reflected_inertia(rotor_inertia: list[float], gears: list[float]) -> float:
    """Rotor inertia seen at the output of a two-stage planetary (first gear ratio is 1)."""
    i_rotor, i_stage1, i_stage2 = rotor_inertia
    _, g2, g3 = gears
    return i_rotor * (g2 * g3) ** 2 + i_stage1 * g3**2 + i_stage2


def _motor_table(raw: dict) -> dict[str, dict[str, float]]:
    table = {}
    for name, spec in raw.items():
        if "same_as" in spec:
            continue
        table[name] = {
            "armature": reflected_inertia(spec["rotor_inertia"], spec["gears"]),
            "effort_limit": float(spec["effort_limit"]),
            "velocity_limit": float(spec["velocity_limit"]),
        }
    for name, spec in raw.items():
        if "same_as" in spec:
            base, k = table[spec["same_as"]], float(spec["multiplier"])
            table[name] = {
                "armature": base["armature"] * k,
                "effort_limit": base["effort_limit"] * k,
                "velocity_limit": base["velocity_limit"],
            }
    return table


def _physics_presets(raw, control_dt: float, source: str) -> tuple[dict[str, PhysicsConfig], str]:
    if not isinstance(raw, dict) or not isinstance(raw.get("presets"), dict) or not raw["presets"]:
        raise PipelineInputError(source, "physics.presets", "must map preset names to their settings")
    presets = {name: PhysicsConfig.from_dict(name, spec, source) for name, spec in raw["presets"].items()}
    for name, preset in presets.items():  # the policy's rate is fixed: a whole number of substeps per control step
        ratio = control_dt / preset.timestep
        if abs(ratio - round(ratio)) > 1e-6:
            raise PipelineInputError(source, f"physics.presets.{name}.timestep",
                                     f"{preset.timestep} s does not divide control_dt {control_dt} s")
    default = raw.get("default")
    if default not in presets:
        raise PipelineInputError(source, "physics.default", f"must name one of {', '.join(presets)}, got {default!r}")
    return presets, default


@lru_cache(maxsize=4)
def load_robot_config(path: str | Path = ROBOT_DIR / "robot.yaml") -> RobotConfig:
    raw = yaml.safe_load(Path(path).read_text())
    presets, default_physics = _physics_presets(raw.get("physics"), float(raw["control_dt"]), str(path))
    motors = _motor_table(raw["motors"])
    omega = 2.0 * math.pi * float(raw["natural_frequency_hz"])
    zeta = float(raw["damping_ratio"])
    names = tuple(raw["joints"])
    motor_of = {n: raw["joints"][n]["motor"] for n in names}
    armature = np.array([motors[motor_of[n]]["armature"] for n in names])
    kp = armature * omega**2
    kd = 2.0 * zeta * armature * omega
    effort = np.array([motors[motor_of[n]]["effort_limit"] for n in names])
    return RobotConfig(
        name=raw["name"],
        joint_names=names,
        default_joint_pos=np.array([float(raw["joints"][n]["default"]) for n in names]),
        armature=armature,
        kp=kp,
        kd=kd,
        effort_limit=effort,
        velocity_limit=np.array([motors[motor_of[n]]["velocity_limit"] for n in names]),
        action_scale=float(raw["action_scale_factor"]) * effort / kp,
        tracked_bodies={k: (v["body"], tuple(v["pos"])) for k, v in raw["tracked_bodies"].items()},
        feet=raw["feet"],
        locked_joints=tuple(raw["locked_joints"]),
        sim_dt=presets[default_physics].timestep,
        control_dt=float(raw["control_dt"]),
        default_root_height=float(raw["default_root_height"]),
        foot_friction=float(raw["foot_friction"]),
        natural_frequency_hz=float(raw["natural_frequency_hz"]),
        damping_ratio=zeta,
        motor_of_joint=motor_of,
        physics_presets=presets,
        default_physics=default_physics,
    )


def add_flat_ground(spec: mujoco.MjSpec) -> None:
    spec.worldbody.add_geom(
        name="ground",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[0.0, 0.0, 0.05],
        rgba=[0.35, 0.4, 0.45, 1.0],
        contype=1,
        conaffinity=1,
        condim=3,
    )


def _add_rendering_extras(spec: mujoco.MjSpec) -> None:
    from pipeline.render.style import style_scene

    style_scene(spec)


def build_spec(
    terrain: TerrainBuilder | None = None,
    visual: bool = True,
    config: RobotConfig | None = None,
    physics: PhysicsConfig | str | None = None,
) -> mujoco.MjSpec:
    """The G1 scene as an editable MjSpec. `visual=False` drops meshes (training needs none).
    `physics`: a preset or its name in robot.yaml (None: the robot's default preset)."""
    cfg = config or load_robot_config()
    phys = physics if isinstance(physics, PhysicsConfig) else cfg.physics(physics)
    spec = mujoco.MjSpec.from_file(str(mjcf_path()))
    phys.apply(spec)

    for sensor in list(spec.sensors):
        spec.delete(sensor)
    for name in cfg.locked_joints:
        spec.delete(spec.joint(name))

    foot_pattern = re.compile(r"^(left|right)_foot([1-7])_collision$")
    for geom in list(spec.geoms):
        if geom.classname.name == "visual" or geom.type == mujoco.mjtGeom.mjGEOM_MESH:
            if not visual:
                spec.delete(geom)
            continue
        if geom.name.endswith("_collision"):
            # Collide with the world only: self contacts cost time and the paper does not need them.
            geom.contype, geom.conaffinity = 0, 1
            foot = foot_pattern.match(geom.name)
            if foot:
                geom.condim, geom.priority = 3, 1
                geom.friction = [cfg.foot_friction, 0.005, 0.0001]
                collides = int(foot.group(2)) in phys.foot_capsules
            else:
                geom.condim = 1
                collides = phys.collisions == "all"
            if not collides:  # kept for drawing, out of the collision pass
                geom.conaffinity = 0
    if not visual:
        for mesh in list(spec.meshes):
            spec.delete(mesh)

    for i, name in enumerate(cfg.joint_names):
        joint = spec.joint(name)
        if joint is None:
            raise KeyError(f"robot.yaml joint {name!r} is not in {mjcf_path()}")
        joint.armature = float(cfg.armature[i])
        act = spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=float(cfg.kp[i]), kv=float(cfg.kd[i]))
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-float(cfg.effort_limit[i]), float(cfg.effort_limit[i])]
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE

    for name, (body_name, pos) in cfg.tracked_bodies.items():
        body = spec.body(body_name)
        if body is None:
            raise KeyError(f"robot.yaml tracked body {name!r}: no body {body_name!r} in the MJCF")
        body.add_site(name=TRACK_SITE_PREFIX + name, pos=list(pos), size=[0.02, 0, 0], group=4,
                      rgba=[0.9, 0.2, 0.2, 1.0])

    (terrain or add_flat_ground)(spec)
    if visual:
        _add_rendering_extras(spec)
    home = spec.add_key(name="home")
    home.qpos = default_qpos(cfg).tolist()
    return spec


def build_model(terrain: TerrainBuilder | None = None, visual: bool = False,
                physics: PhysicsConfig | str | None = None) -> mujoco.MjModel:
    return build_spec(terrain=terrain, visual=visual, physics=physics).compile()


def default_qpos(cfg: RobotConfig | None = None) -> np.ndarray:
    cfg = cfg or load_robot_config()
    return np.concatenate([[0.0, 0.0, cfg.default_root_height, 1.0, 0.0, 0.0, 0.0], cfg.default_joint_pos])


def joint_qpos_indices(model: mujoco.MjModel, joint_names: tuple[str, ...]) -> np.ndarray:
    return np.array([model.jnt_qposadr[model.joint(n).id] for n in joint_names])


def joint_dof_indices(model: mujoco.MjModel, joint_names: tuple[str, ...]) -> np.ndarray:
    return np.array([model.jnt_dofadr[model.joint(n).id] for n in joint_names])


def site_ids(model: mujoco.MjModel, site_names: tuple[str, ...]) -> np.ndarray:
    return np.array([model.site(n).id for n in site_names])


def joint_limits(model: mujoco.MjModel, joint_names: tuple[str, ...]) -> np.ndarray:
    """(J, 2) position limits in the given joint order."""
    return np.array([model.jnt_range[model.joint(n).id] for n in joint_names])
