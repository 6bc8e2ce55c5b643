"""Inverse dynamics of a G1 reference motion: the joint torques that would produce it.

mj_inverse, with contacts disabled, gives the generalised forces of the whole motion. Its six
floating-base rows are the wrench that gravity and the motion's accelerations ask of the ground: the
feet in contact carry it (least-norm 6-D wrenches at the foot bodies), and the joints supply the rest
through the feet's Jacobian. In the air no foot carries anything and the joints get their own rows.

Two readers: `envs/feedforward.py` aims the PD actuators at these torques, clipped to the motors'
limits, and `retarget/quality.py` reports how far beyond those limits a clip asks the motors to go.
"""

from __future__ import annotations

import copy

import mujoco
import numpy as np
from scipy.signal import savgol_filter

from pipeline.motion.motion import Motion
from pipeline.robot.g1 import RobotConfig, build_model, load_robot_config


def joint_torques(motion: Motion, feet_in_contact: np.ndarray, robot: RobotConfig | None = None,
                  model: mujoco.MjModel | None = None, qvel: np.ndarray | None = None,
                  qacc: np.ndarray | None = None) -> np.ndarray:
    """(T, J) joint torques (N·m, not clipped) that produce `motion`, its base carried by the feet marked
    in `feet_in_contact` (T, 2: left, right). Velocities and accelerations default to the motion's own
    finite differences; pass smoothed ones for a clip whose second differences are mostly noise.
    `motion`'s joints must be in the model's order."""
    robot = robot or load_robot_config()
    model = _without_contacts(model or build_model())
    model_joints = tuple(model.joint(i).name for i in range(model.njnt) if model.jnt_type[i] != mujoco.mjtJoint.mjJNT_FREE)
    if tuple(motion.joint_names) != model_joints:
        raise ValueError("joint_torques: the motion's joints must be in the model's order (Motion.reorder_joints)")
    data = mujoco.MjData(model)
    qpos = motion.qpos()
    qvel = motion.qvel() if qvel is None else qvel
    qacc = np.gradient(qvel, motion.dt, axis=0) if qacc is None else qacc
    feet = [model.body(robot.feet[side]["body"]).id for side in ("left", "right")]
    torques = np.zeros((motion.num_frames, model.nv - 6))
    for t in range(motion.num_frames):
        data.qpos[:], data.qvel[:], data.qacc[:] = qpos[t], qvel[t], qacc[t]
        torques[t] = _carried_torques(model, data, [f for f, standing in zip(feet, feet_in_contact[t]) if standing])
    return torques


def stance_torques(robot: RobotConfig | None = None, model: mujoco.MjModel | None = None) -> np.ndarray:
    """(J,) joint torques that hold the default pose still, its weight carried by both feet."""
    from pipeline.robot.g1 import default_qpos

    robot = robot or load_robot_config()
    model = _without_contacts(model or build_model())
    data = mujoco.MjData(model)
    data.qpos[:] = default_qpos(robot)
    return _carried_torques(model, data, [model.body(robot.feet[side]["body"]).id for side in ("left", "right")])


def _carried_torques(model: mujoco.MjModel, data: mujoco.MjData, standing_feet: list[int]) -> np.ndarray:
    """Joint torques of the state in `data` (qpos, qvel, qacc), the base wrench carried by `standing_feet`."""
    mujoco.mj_inverse(model, data)
    generalized = data.qfrc_inverse.copy()
    rows = []
    jac_pos, jac_rot = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    for foot in standing_feet:
        mujoco.mj_jacBody(model, data, jac_pos, jac_rot, foot)
        rows.append(np.vstack([jac_pos, jac_rot]))
    if not rows:
        return generalized[6:]
    jac = np.vstack(rows)  # (6·feet, nv)
    wrench, *_ = np.linalg.lstsq(jac[:, :6].T, generalized[:6], rcond=None)
    return generalized[6:] - jac[:, 6:].T @ wrench


def fit_half_window(window_s: float, dt: float) -> int:
    """Frames either side of the centre of a local fit spanning about `window_s` (an odd window of
    2·h + 1 frames): the smoothers below use it, and so do checks that must keep a fit off a contact change."""
    return int(round(window_s / dt / 2))


def smoothed_velocity_and_acceleration(motion: Motion, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(T, nv) generalised velocities and accelerations from local cubic fits over `window_s`: a clip
    estimated from video jitters at a rate no PD-tracked robot follows, and raw second differences
    turn that jitter into torques several times the real ones."""
    qvel = motion.qvel()
    window = 2 * fit_half_window(window_s, motion.dt) + 1
    if motion.num_frames < window or window < 5:
        return qvel, np.gradient(qvel, motion.dt, axis=0)
    return (savgol_filter(qvel, window, 3, axis=0),
            savgol_filter(qvel, window, 3, deriv=1, delta=motion.dt, axis=0))


def _without_contacts(model: mujoco.MjModel) -> mujoco.MjModel:
    """A copy whose inverse dynamics ignore contacts (the feet's wrenches are solved for instead)."""
    model = copy.copy(model)
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    return model
