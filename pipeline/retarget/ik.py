"""Frame-by-frame IK driven by the task table (GMR style), with mink or placo behind it.

mink: one FrameTask per table row on the `track_<name>` sites, a posture task towards the default
pose (regularisation), joint-position and joint-velocity limits, `iterations` QP steps per frame
warm-started from the previous frame's solution. The velocity limit is applied per frame (each of
the `iterations` steps gets its share of the frame time), so the solution never moves a joint
faster than the motor can.
"""

from __future__ import annotations

import mujoco
import numpy as np

from pipeline.retarget.config import RetargetConfig
from pipeline.robot.g1 import default_qpos, joint_qpos_indices, load_robot_config


def _points_task_class():
    import mink

    class PointsTask(mink.Task):
        """Position-only targets for several sites as one task: one stacked residual instead of
        one FrameTask (SE3 log, its Jacobian, weighting) per site; same QP, less Python per step."""

        def __init__(self, model: mujoco.MjModel, site_names: list[str], weights: list[float]):
            super().__init__(cost=np.repeat(np.asarray(weights, float), 3), gain=1.0, lm_damping=0.0)
            self.site_ids = [model.site(n).id for n in site_names]
            self.targets = np.zeros((len(site_names), 3))
            self._jac = np.zeros((3 * len(site_names), model.nv))

        def set_weight(self, index: int, weight: float) -> None:
            self.cost[3 * index : 3 * index + 3] = weight

        def compute_error(self, configuration) -> np.ndarray:
            return (configuration.data.site_xpos[self.site_ids] - self.targets).ravel()

        def compute_jacobian(self, configuration) -> np.ndarray:
            for i, site in enumerate(self.site_ids):
                mujoco.mj_jacSite(configuration.model, configuration.data, self._jac[3 * i : 3 * i + 3], None, site)
            return self._jac

        def compute_qp_residual(self, configuration):
            return self._weighted_residual(self.compute_error(configuration), self.compute_jacobian(configuration))

    return PointsTask


class MinkRetargeter:
    def __init__(self, model: mujoco.MjModel, cfg: RetargetConfig, frame_dt: float):
        import mink

        self._mink = mink
        self.model = model
        self.cfg = cfg
        self.robot = load_robot_config()
        self.configuration = mink.Configuration(model)
        self.configuration.update(default_qpos(self.robot))
        self.frame_dt = frame_dt
        self.frames = tuple(name for name, row in cfg.task_table.items()
                            if row.position_weight > 0 or row.orientation_weight > 0)
        # Frames with an orientation target get a FrameTask; position-only ones share a PointsTask.
        table = cfg.task_table
        self.tasks = {
            name: mink.FrameTask(f"track_{name}", "site", position_cost=table[name].position_weight,
                                 orientation_cost=table[name].orientation_weight)
            for name in self.frames if table[name].orientation_weight > 0
        }
        self.point_names = [name for name in self.frames if table[name].orientation_weight == 0]
        self.points = _points_task_class()(model, [f"track_{n}" for n in self.point_names],
                                           [table[n].position_weight for n in self.point_names])
        self.posture = mink.PostureTask(model, cost=cfg.posture_weight)
        self.posture.set_target(default_qpos(self.robot))
        vmax = cfg.velocity_limit_scale * self.robot.velocity_limit
        self.limits = [
            mink.ConfigurationLimit(model),
            mink.VelocityLimit(model, dict(zip(self.robot.joint_names, vmax))),
        ]
        self.qpos_index = joint_qpos_indices(model, self.robot.joint_names)

    def set_weights(self, name: str, position: float, orientation: float) -> None:
        if name in self.tasks:
            self.tasks[name].set_position_cost(position)
            self.tasks[name].set_orientation_cost(orientation)
        elif name in self.point_names:
            self.points.set_weight(self.point_names.index(name), position)

    def solve(self, targets: dict[str, np.ndarray], iterations: int, first: bool = False) -> np.ndarray:
        """targets: frame -> (7,) wxyz_xyz world pose. Returns qpos (nq,)."""
        mink = self._mink
        for name, task in self.tasks.items():
            task.set_target(mink.SE3(wxyz_xyz=targets[name]))
        for i, name in enumerate(self.point_names):
            self.points.targets[i] = targets[name][4:]
        tasks = [*self.tasks.values(), self.points, self.posture]
        # The first frame starts from the default pose: let it move as far as it must.
        dt = 1.0 if first else self.frame_dt / iterations
        for _ in range(iterations):
            v = mink.solve_ik(self.configuration, tasks, dt, self.cfg.qp_solver,
                              damping=self.cfg.damping, limits=self.limits)
            self.configuration.integrate_inplace(v, dt)
        return self.configuration.q.copy()


class PlacoRetargeter:
    """The same table on placo's KinematicsSolver. placo reads URDF only (not MJCF), so the URDF is
    written in memory from the compiled MuJoCo model (`urdf.mjcf_to_urdf`), tracked sites as frames."""

    def __init__(self, model: mujoco.MjModel, cfg: RetargetConfig, frame_dt: float):
        import placo

        from pipeline.retarget.urdf import mjcf_to_urdf

        self.cfg = cfg
        self.robot_cfg = load_robot_config()
        self.model = model
        self.robot = placo.RobotWrapper("", 0, mjcf_to_urdf(model))
        self.solver = placo.KinematicsSolver(self.robot)
        self.solver.mask_fbase(False)
        self.solver.enable_joint_limits(True)
        self.solver.enable_velocity_limits(True)
        self.solver.dt = frame_dt
        self.frame_dt = frame_dt
        self.frames = tuple(name for name, row in cfg.task_table.items()
                            if row.position_weight > 0 or row.orientation_weight > 0)
        self.tasks = {}
        for name in self.frames:
            task = self.solver.add_frame_task(f"track_{name}", np.eye(4))
            task.configure(f"track_{name}", "soft", cfg.task_table[name].position_weight,
                           cfg.task_table[name].orientation_weight)
            self.tasks[name] = task
        self.posture = self.solver.add_joints_task()
        self.posture.set_joints(dict(zip(self.robot_cfg.joint_names, self.robot_cfg.default_joint_pos)))
        self.posture.configure("posture", "soft", cfg.posture_weight)
        self.solver.add_regularization_task(cfg.damping)
        q0 = default_qpos(self.robot_cfg)
        self._set_state(q0)
        self.qpos_index = joint_qpos_indices(model, self.robot_cfg.joint_names)

    def _set_state(self, qpos: np.ndarray) -> None:
        # placo's floating base is xyz + quaternion (x, y, z, w), then joints in URDF order.
        self.robot.set_T_world_frame("pelvis", _pose_matrix(qpos[3:7], qpos[:3]))
        for name, value in zip(self.robot_cfg.joint_names, qpos[7:]):
            self.robot.set_joint(name, float(value))
        self.robot.update_kinematics()

    def set_weights(self, name: str, position: float, orientation: float) -> None:
        if name in self.tasks:
            self.tasks[name].configure(f"track_{name}", "soft", position, orientation)

    def solve(self, targets: dict[str, np.ndarray], iterations: int, first: bool = False) -> np.ndarray:
        for name, task in self.tasks.items():
            task.T_world_frame = _pose_matrix(targets[name][:4], targets[name][4:])
        self.solver.enable_velocity_limits(not first)
        self.solver.dt = self.frame_dt / iterations  # the velocity limit holds per frame, not per step
        for _ in range(iterations):
            self.solver.solve(True)
            self.robot.update_kinematics()
        t_world = self.robot.get_T_world_frame("pelvis")
        from pipeline.common import quat

        qpos = np.zeros(self.model.nq)
        qpos[:3] = t_world[:3, 3]
        qpos[3:7] = quat.from_matrix(t_world[:3, :3])
        qpos[self.qpos_index] = [self.robot.get_joint(n) for n in self.robot_cfg.joint_names]
        return qpos


def _pose_matrix(wxyz: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    from pipeline.common import quat

    out = np.eye(4)
    out[:3, :3] = quat.to_matrix(np.asarray(wxyz, float))
    out[:3, 3] = xyz
    return out


def make_retargeter(model: mujoco.MjModel, cfg: RetargetConfig, frame_dt: float):
    if cfg.solver == "placo":
        return PlacoRetargeter(model, cfg, frame_dt)
    return MinkRetargeter(model, cfg, frame_dt)
