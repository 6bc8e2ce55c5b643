"""Inverse dynamics of a reference (robot/dynamics.py), the feet that carry it (motion/feet.py), and the
retarget's torque check built on both."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from pipeline.envs.feedforward import reference_joint_torques
from pipeline.motion.feet import detect_foot_contacts, foot_height_and_speed
from pipeline.motion.motion import RobotKinematics
from pipeline.retarget.quality import torque_report
from pipeline.robot.dynamics import joint_torques
from pipeline.robot.g1 import build_model, default_qpos, load_robot_config

FPS = 50.0


@pytest.fixture(scope="module")
def kin():
    return RobotKinematics()


def _motion(kin, joint_pos: np.ndarray, floor_z: float = 0.0, fps: float = FPS):
    """The default pose's root with `joint_pos` (T, J), moved frame by frame so the feet stay planted where
    they are in the first frame, with their lowest sole point on a floor at `floor_z`."""
    q = default_qpos()
    t = len(joint_pos)
    root = np.repeat(q[None, :3], t, axis=0)
    quat = np.repeat(q[None, 3:7], t, axis=0)
    loose = kin.motion(fps, root, quat, joint_pos)
    ankle = loose.body_pos[:, loose.body_index("left_ankle")]
    root -= ankle - ankle[:1]  # the legs bend; the feet stay put
    root[:, 2] += floor_z - foot_height_and_speed(kin.motion(fps, root, quat, joint_pos))[0].min()
    return kin.motion(fps, root, quat, joint_pos)


def _standing(kin, frames: int = 20, floor_z: float = 0.0):
    q = default_qpos()
    return _motion(kin, np.repeat(q[None, kin.qpos_index], frames, axis=0), floor_z)


def _squat(kin, still_frames: int = 0) -> np.ndarray:
    """(T, J) joints of one squat down and up over 41 frames (knees 1 rad, hips and ankles half as far
    the other way so the feet stay flat), with `still_frames` of standing before and after."""
    q = default_qpos()[kin.qpos_index]
    wave = 0.5 * (1.0 - np.cos(np.linspace(0.0, 2.0 * np.pi, 41)))  # 0 -> 1 -> 0
    bend = np.zeros_like(q)
    for name, angle in (("hip_pitch_joint", -0.5), ("knee_joint", 1.0), ("ankle_pitch_joint", -0.5)):
        for side in ("left", "right"):
            bend[kin.joint_names.index(f"{side}_{name}")] = angle
    still = np.repeat(q[None], still_frames, axis=0)
    return np.concatenate([still, q + wave[:, None] * bend, still])



def test_standing_torques_hold_the_robot_up_through_real_contacts(kin):
    """Applied to a G1 standing on MuJoCo's floor with its actuators off, the inverse-dynamics torques of
    standing still keep it from sagging: with them the base's first vertical acceleration is small, with
    no torques it drops at most of g."""
    motion = _standing(kin)
    torques = reference_joint_torques(motion)
    model = build_model()
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_ACTUATION
    data = mujoco.MjData(model)
    fall = {}
    for name, tau in (("held", torques[0]), ("limp", np.zeros_like(torques[0]))):
        data.qpos[:] = motion.qpos()[0]
        data.qpos[2] -= 1e-3  # soles just into the floor, so the contacts are active
        data.qvel[:] = 0.0
        data.qfrc_applied[:] = 0.0
        data.qfrc_applied[6:] = tau
        mujoco.mj_forward(model, data)
        fall[name] = data.qacc[2]
    assert abs(fall["held"]) < 1.0, fall
    assert fall["limp"] < -4.0, fall


def test_feet_on_a_box_carry_the_robot_as_on_the_floor(kin):
    """Standing still on a 0.3 m box is standing still: the same torques as on the floor. The contacts come
    from each stance's own floor height, so the feet on the box carry the body (a test of height above
    z = 0 would leave the legs to hold only themselves)."""
    floor, box = _standing(kin), _standing(kin, floor_z=0.3)
    assert detect_foot_contacts(floor).all() and detect_foot_contacts(box).all()
    on_floor, on_box = reference_joint_torques(floor), reference_joint_torques(box)
    np.testing.assert_allclose(on_box, on_floor, atol=1e-9)
    knees = [kin.joint_names.index(f"{side}_knee_joint") for side in ("left", "right")]
    assert np.all(np.abs(on_floor[:, knees]) > 5.0)  # the knees carry the weight (about 10 N·m each)


def test_joint_torques_grow_with_the_square_of_speed(kin):
    """A squat played twice as fast: its torques beyond the static ones (gravity) are four times as large,
    since accelerations and the velocity-product terms both scale with the square of the speed."""
    joints = _squat(kin)
    feet = np.ones((len(joints), 2), dtype=bool)
    slow, fast = _motion(kin, joints, fps=FPS), _motion(kin, joints, fps=2 * FPS)
    zero = np.zeros_like(slow.qvel())
    static = joint_torques(slow, feet, qvel=zero, qacc=zero)
    dynamic_slow = joint_torques(slow, feet) - static
    dynamic_fast = joint_torques(fast, feet) - static
    assert np.abs(dynamic_slow).max() > 1.0  # the squat really moves
    np.testing.assert_allclose(dynamic_fast, 4.0 * dynamic_slow, atol=1e-6 * np.abs(dynamic_slow).max())


def test_joint_torques_need_the_models_joint_order(kin):
    motion = _standing(kin, frames=3)
    shuffled = motion.reorder_joints(tuple(reversed(motion.joint_names)))
    with pytest.raises(ValueError, match="model's order"):
        joint_torques(shuffled, np.ones((3, 2), dtype=bool))


def test_torque_report_standing_and_a_squat_too_fast(kin):
    """Standing still asks a fraction of every motor's limit. A squat at 3.5 times the speed asks the legs'
    pitch joints for more than they have, and the report says which and when."""
    robot, model = load_robot_config(), build_model()
    calm = torque_report(_standing(kin, frames=40), model, robot)
    assert calm["peak_effort_ratio"] < 0.5 and calm["frames_over_limit"] == 0 and calm["joints_over_limit"] == {}
    assert calm["frames_checked"] == 40

    report = torque_report(_motion(kin, _squat(kin, still_frames=10), fps=3.5 * FPS), model, robot)
    assert report["peak_effort_ratio"] > 1.0 and report["frames_over_limit"] > 0
    assert report["peak_joint"] in report["joints_over_limit"]
    assert max(report["joints_over_limit"].values()) == pytest.approx(report["peak_effort_ratio"])
    assert all(name.split("_", 1)[1] in ("hip_pitch_joint", "knee_joint", "ankle_pitch_joint")
               for name in report["joints_over_limit"]), report
    assert 10 / (3.5 * FPS) < report["peak_time_s"] < 51 / (3.5 * FPS)
