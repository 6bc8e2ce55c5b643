"""The simulation model: the G1 scene plus the sensors the backends read after a step.

Both backends read everything the environment needs from `sensordata` (one contiguous row per
world), so no Python loop over worlds runs after a step. The sensors, all named `sim_*`:

  * framepos of every tracked site, in robot order, then framequat of every tracked site
    (contiguous, so the rows reshape to (S, 3) and (S, 4) without a gather);
  * one contact sensor per foot body ("found": number of contacts of that body's geoms; the robot
    collides with the world only, so every contact of a foot is a foot-vs-world contact);
  * actuatorfrc of every actuator, in action order.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.robot.g1 import (
    PhysicsConfig,
    RobotConfig,
    TerrainBuilder,
    build_spec,
    load_robot_config,
)

SENSOR_PREFIX = "sim_"
FOOT_SIDES = ("left", "right")

# mjSENS_CONTACT intprm: data spec bit 0 = "found"; reduce 1 = "mindist"; keep 1 contact.
_CONTACT_FOUND, _REDUCE_MINDIST, _CONTACT_NUM = 1, 1, 1


def add_sim_sensors(spec: mujoco.MjSpec, config: RobotConfig | None = None) -> mujoco.MjSpec:
    """Adds the backends' sensors to a G1 spec (from `pipeline.robot.g1.build_spec`), in place."""
    cfg = config or load_robot_config()
    site_names = cfg.tracked_site_names
    for name in site_names:
        spec.add_sensor(name=f"{SENSOR_PREFIX}pos_{name}", type=mujoco.mjtSensor.mjSENS_FRAMEPOS,
                        objtype=mujoco.mjtObj.mjOBJ_SITE, objname=name)
    for name in site_names:
        spec.add_sensor(name=f"{SENSOR_PREFIX}quat_{name}", type=mujoco.mjtSensor.mjSENS_FRAMEQUAT,
                        objtype=mujoco.mjtObj.mjOBJ_SITE, objname=name)
    for side in FOOT_SIDES:
        sensor = spec.add_sensor(name=f"{SENSOR_PREFIX}contact_{side}", type=mujoco.mjtSensor.mjSENS_CONTACT,
                                 objtype=mujoco.mjtObj.mjOBJ_BODY, objname=cfg.feet[side]["body"])
        sensor.intprm = [_CONTACT_FOUND, _REDUCE_MINDIST, _CONTACT_NUM]
    for name in cfg.joint_names:  # actuators are named after their joints, in action order
        spec.add_sensor(name=f"{SENSOR_PREFIX}frc_{name}", type=mujoco.mjtSensor.mjSENS_ACTUATORFRC,
                        objtype=mujoco.mjtObj.mjOBJ_ACTUATOR, objname=name)
    return spec


def build_sim_model(terrain: TerrainBuilder | None = None, config: RobotConfig | None = None,
                    physics: PhysicsConfig | str | None = None) -> mujoco.MjModel:
    """The G1 training model (no meshes) with the backends' sensors, under physics preset `physics`
    (a name in robot.yaml; None: its default). Both backends take this one model."""
    cfg = config or load_robot_config()
    return add_sim_sensors(build_spec(terrain=terrain, visual=False, config=cfg, physics=physics), cfg).compile()


def sim_model_from(model_or_spec: mujoco.MjModel | mujoco.MjSpec) -> mujoco.MjModel:
    """Accepts a compiled model that already has the sensors, or a spec to which they are added."""
    if isinstance(model_or_spec, mujoco.MjSpec):
        spec = model_or_spec.copy()
        if spec.sensor(f"{SENSOR_PREFIX}pos_{load_robot_config().tracked_site_names[0]}") is None:
            add_sim_sensors(spec)
        return spec.compile()
    if isinstance(model_or_spec, mujoco.MjModel):
        return model_or_spec
    raise PipelineInputError("backend", "model", f"expected an MjModel or MjSpec, got {type(model_or_spec).__name__}")


@dataclass(frozen=True)
class SensorLayout:
    """Where each quantity sits in a sensordata row (start, stop), plus the state's slices."""

    site_pos: tuple[int, int]
    site_quat: tuple[int, int]
    foot_contact: tuple[int, int]
    actuator_force: tuple[int, int]
    num_sites: int
    site_names: tuple[str, ...]


def _block(model: mujoco.MjModel, names: list[str], dim: int) -> tuple[int, int]:
    """(start, stop) of sensors `names`, which must lie contiguous in sensordata, `dim` values each."""
    adrs = []
    for name in names:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, name)
        if sid < 0:
            raise PipelineInputError(
                "backend", "model",
                f"sensor {name!r} missing: build the model with pipeline.sim.model.build_sim_model(terrain) "
                "or pass the MjSpec (the backend then adds its sensors)",
            )
        if model.sensor_dim[sid] != dim:
            raise PipelineInputError("backend", "model", f"sensor {name!r} has dim {model.sensor_dim[sid]}, expected {dim}")
        adrs.append(int(model.sensor_adr[sid]))
    start = adrs[0]
    if adrs != list(range(start, start + dim * len(names), dim)):
        raise PipelineInputError("backend", "model", f"sensors {names[0]}.. are not contiguous in sensordata")
    return start, start + dim * len(names)


def sensor_layout(model: mujoco.MjModel, config: RobotConfig | None = None) -> SensorLayout:
    cfg = config or load_robot_config()
    sites = cfg.tracked_site_names
    return SensorLayout(
        site_pos=_block(model, [f"{SENSOR_PREFIX}pos_{s}" for s in sites], 3),
        site_quat=_block(model, [f"{SENSOR_PREFIX}quat_{s}" for s in sites], 4),
        foot_contact=_block(model, [f"{SENSOR_PREFIX}contact_{side}" for side in FOOT_SIDES], 1),
        actuator_force=_block(model, [f"{SENSOR_PREFIX}frc_{j}" for j in cfg.joint_names], 1),
        num_sites=len(sites),
        site_names=sites,
    )


def check_actuators_in_joint_order(model: mujoco.MjModel, config: RobotConfig | None = None) -> None:
    cfg = config or load_robot_config()
    names = tuple(model.actuator(i).name for i in range(model.nu))
    if names != cfg.joint_names:
        raise PipelineInputError("backend", "model", "actuators are not the robot's 27 joints in action order")


def default_state_qpos(model: mujoco.MjModel) -> np.ndarray:
    """qpos of the 'home' keyframe if there is one, else the model's qpos0."""
    key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "home")
    return model.key_qpos[key].copy() if key >= 0 else model.qpos0.copy()


def geom_bounds(geom_type: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounding radius (n,) and local AABB half-sizes (n, 3) of primitive geoms of given sizes.

    The broad phase culls with geom_rbound / geom_aabb, so resizing a geom (terrain per ψ) must
    move them too, or a grown box would be missed by the collision pass.
    """
    size = np.asarray(size, dtype=np.float64).reshape(-1, 3)
    geom_type = np.broadcast_to(np.asarray(geom_type), (size.shape[0],))
    rbound = np.zeros(size.shape[0])
    half = np.zeros_like(size)
    G = mujoco.mjtGeom
    BOX, SPHERE, CAPSULE, CYLINDER, ELLIPSOID, PLANE = (int(g) for g in (
        G.mjGEOM_BOX, G.mjGEOM_SPHERE, G.mjGEOM_CAPSULE, G.mjGEOM_CYLINDER, G.mjGEOM_ELLIPSOID, G.mjGEOM_PLANE))
    for i, (t, s) in enumerate(zip(geom_type.astype(int).tolist(), size)):
        if t == BOX:
            half[i], rbound[i] = s, np.linalg.norm(s)
        elif t == SPHERE:
            half[i], rbound[i] = s[0], s[0]
        elif t in (CAPSULE, CYLINDER):
            half[i] = (s[0], s[0], s[1] + (s[0] if t == CAPSULE else 0.0))
            rbound[i] = s[1] + s[0] if t == CAPSULE else np.hypot(s[0], s[1])
        elif t == ELLIPSOID:
            half[i], rbound[i] = s, s.max()
        elif t == PLANE:
            # Planes are infinite for collision whatever their drawn size, as the compiler sets them.
            half[i], rbound[i] = (1e10, 1e10, 5e9), 0.0
        else:
            raise PipelineInputError("backend", "geom_size", f"cannot resize geoms of type {int(t)} (only primitives)")
    return rbound, half


def refresh_body_bvh(model: mujoco.MjModel, body: int) -> None:
    """Recomputes the compile-time bounding-volume tree of `body` after its geoms moved or grew.

    MuJoCo's midphase culls geom pairs with per-body trees (bvh_aabb, in the body's inertial
    frame) that the compiler fills once; a terrain geom moved by set_model_field would otherwise
    be tested against its old box and never touched. Meant for the world body (terrain): its
    leaves match the compiler's exactly (tested); for robot links the compiler bounds some
    primitives more tightly than this does.
    """
    start, count = int(model.body_bvhadr[body]), int(model.body_bvhnum[body])
    if count <= 0:
        return
    rot_i = np.empty(9)
    mujoco.mju_quat2Mat(rot_i, model.body_iquat[body])
    rot_i = rot_i.reshape(3, 3)
    rot_g = np.empty(9)
    for node in range(start + count - 1, start - 1, -1):  # children follow their parent
        geom = int(model.bvh_nodeid[node])
        left, right = (int(c) for c in model.bvh_child[node])
        if geom >= 0 and left < 0 and right < 0:
            mujoco.mju_quat2Mat(rot_g, model.geom_quat[geom])
            rg = rot_g.reshape(3, 3)
            center_b = model.geom_pos[geom] + rg @ model.geom_aabb[geom, :3]
            half_b = np.abs(rg) @ model.geom_aabb[geom, 3:]
            center = rot_i.T @ (center_b - model.body_ipos[body])
            half = np.abs(rot_i.T) @ half_b
        else:
            kids = [start + c for c in (left, right) if c >= 0]
            lo = np.min([model.bvh_aabb[k, :3] - model.bvh_aabb[k, 3:] for k in kids], axis=0)
            hi = np.max([model.bvh_aabb[k, :3] + model.bvh_aabb[k, 3:] for k in kids], axis=0)
            center, half = (lo + hi) / 2, (hi - lo) / 2
        model.bvh_aabb[node, :3], model.bvh_aabb[node, 3:] = center, half
