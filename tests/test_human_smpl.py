"""SMPL skeleton FK, shape model, conversions, the human dataset and the synthetic sample."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.common import quat
from pipeline.common.errors import PipelineInputError
from pipeline.human import smpl
from pipeline.human.frames import detect_up_axis, up_rotation
from pipeline.human.importers import load_human_motion
from pipeline.human.sample import JUMP_DISTANCE_M, SAMPLE_PATH, write_sample

J = {name: i for i, name in enumerate(smpl.SMPL_JOINT_NAMES)}


def test_neutral_table_matches_the_mannequin_calibration():
    model = smpl.shape_model()
    if model is None:
        pytest.skip("mannequin-x not installed")
    np.testing.assert_allclose(smpl.NEUTRAL_REST_JOINTS, model.joint_rest, atol=6e-5)
    assert abs(model.height(np.zeros(10)) - smpl.NEUTRAL_HEIGHT) < 1e-3


def test_rest_pose_joint_heights_of_the_neutral_body():
    rest = smpl.NEUTRAL_REST_JOINTS
    pos, rot = smpl.forward_kinematics(np.zeros((1, 22, 3)), np.zeros((1, 3)), rest)
    np.testing.assert_allclose(pos[0], rest, atol=1e-12)
    np.testing.assert_allclose(rot[0], np.tile([1.0, 0, 0, 0], (22, 1)), atol=1e-12)
    sole = smpl.NEUTRAL_SOLE_Y
    height = {name: pos[0, J[name], 1] - sole for name in J}
    # A 1.72 m body: pelvis ~0.95 m, head joint ~1.57 m, ankles ~7.5 cm, knees ~0.48 m above the sole.
    assert 0.90 < height["pelvis"] < 1.00
    assert 0.58 < height["head"] - height["pelvis"] < 0.66
    assert 0.06 < height["left_ankle"] < 0.09 and 0.06 < height["right_ankle"] < 0.09
    assert 0.44 < height["left_knee"] < 0.52
    assert 1.68 < smpl.NEUTRAL_HEIGHT < 1.76
    # T-pose arm span wrist to wrist ~1.34 m; left is +x.
    assert 1.25 < pos[0, J["left_wrist"], 0] - pos[0, J["right_wrist"], 0] < 1.45


def test_known_rotation_knee_bend_and_root_pivot():
    rest = smpl.NEUTRAL_REST_JOINTS
    rv = np.zeros((1, 22, 3))
    rv[0, J["left_knee"]] = [np.pi / 2, 0, 0]  # +90 deg about x: the shin swings backward (-z)
    pos, _ = smpl.forward_kinematics(rv, np.zeros((1, 3)), rest)
    shin = rest[J["left_ankle"]] - rest[J["left_knee"]]
    expected = rest[J["left_knee"]] + np.array([shin[0], -shin[2], shin[1]])
    np.testing.assert_allclose(pos[0, J["left_ankle"]], expected, atol=1e-12)
    assert pos[0, J["left_ankle"], 2] < rest[J["left_knee"], 2] - 0.3
    # The root rotates about the rest pelvis: pelvis stays at J0 + trans.
    rv = np.zeros((1, 22, 3))
    rv[0, 0] = [0, 0, 1.0]
    trans = np.array([[0.5, -0.2, 0.1]])
    pos, _ = smpl.forward_kinematics(rv, trans, rest)
    np.testing.assert_allclose(pos[0, 0], rest[0] + trans[0], atol=1e-12)


def test_betas_change_size_linearly():
    if smpl.shape_model() is None:
        pytest.skip("mannequin-x not installed")
    tall = smpl.standing_height(np.array([-2.0] + [0] * 9))
    short = smpl.standing_height(np.array([2.0] + [0] * 9))
    assert abs(tall - short) > 0.1  # beta 0 is mostly stature
    mid = smpl.rest_joints(np.zeros(10))
    np.testing.assert_allclose(0.5 * (smpl.rest_joints(np.full(10, 1.0)) + smpl.rest_joints(np.full(10, -1.0))), mid, atol=1e-12)


def test_height_scale_fallback():
    rest = smpl.rest_joints(height=2 * smpl.NEUTRAL_HEIGHT)
    np.testing.assert_allclose(rest, 2 * smpl.NEUTRAL_REST_JOINTS)


def test_axis_conventions():
    # y-up -> z-up: +y goes to +z, +z (front of a y-up body) goes to -y... and x stays.
    q = up_rotation("+y")
    np.testing.assert_allclose(quat.rotate(q, np.array([0, 1.0, 0])), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(quat.rotate(q, np.array([1.0, 0, 0])), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(quat.rotate(q, np.array([0, 0, 1.0])), [0, -1, 0], atol=1e-12)
    for axis in ("+x", "-x", "-y", "+z", "-z"):
        index, sign = {"x": 0, "y": 1, "z": 2}[axis[1]], (1 if axis[0] == "+" else -1)
        v = np.zeros(3)
        v[index] = sign
        np.testing.assert_allclose(quat.rotate(up_rotation(axis), v), [0, 0, 1], atol=1e-12)
    # Upright neutral body in its own frame is "+y" up.
    pos, _ = smpl.forward_kinematics(np.zeros((3, 22, 3)), np.zeros((3, 3)), smpl.NEUTRAL_REST_JOINTS)
    assert detect_up_axis(pos) == "+y"


# --- dataset round trip ----------------------------------------------------------------------

def test_human_dataset_round_trip(tmp_path):
    pytest.importorskip("pipeline.dataset.lerobot")
    from pipeline.human.dataset import read_human, write_human

    m = load_human_motion(write_sample(tmp_path / "s.npz"))
    write_human(tmp_path / "human", m)
    back = read_human(tmp_path / "human")
    for key in ("joint_pos", "joint_quat", "local_rotvec", "root_trans", "betas"):
        assert np.array_equal(getattr(m, key), getattr(back, key)), key
    assert (back.fps, back.name, back.height) == (m.fps, m.name, m.height)
    with pytest.raises(PipelineInputError):
        read_human(tmp_path / "nothing_here")


# --- synthetic sample ------------------------------------------------------------------------

def test_bundled_sample_is_what_the_script_writes(tmp_path):
    fresh = write_sample(tmp_path / "again.npz")
    with np.load(fresh) as a, np.load(SAMPLE_PATH) as b:
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            assert np.array_equal(a[key], b[key]), key
        assert "SYNTHETIC" in str(b["note"])


def _com_and_zmp_x(pos: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The centre of mass (T, 3) of joint positions and the x of its path's zero-moment point,
    x - z x'' / (g + z'') (T,)."""
    com = smpl.center_of_mass(pos)
    acc = np.gradient(np.gradient(com, dt, axis=0), dt, axis=0)
    return com, com[:, 0] - com[:, 2] * acc[:, 0] / (9.81 + acc[:, 2])


def test_sample_far_jump_physics(sample_clip):
    clip = sample_clip
    m = load_human_motion(SAMPLE_PATH)
    assert 2.0 <= m.duration <= 3.0 and m.fps == 30.0
    pos = m.joint_pos
    sole = pos[:, [7, 8, 10, 11], 2].min(axis=1)
    # Feet land JUMP_DISTANCE_M ahead, facing +x, and stay on the floor before/after the flight.
    feet_x = pos[:, [10, 11], 0].mean(axis=1)
    assert abs(feet_x[-1] - feet_x[0] - JUMP_DISTANCE_M) < 0.02
    ground = np.r_[0 : clip.takeoff_frame - 3, clip.touchdown_frame + 1 : m.num_frames]
    assert np.all(sole[ground] < 0.09) and np.all(sole[ground] > -0.005)
    flight = slice(clip.takeoff_frame + 1, clip.touchdown_frame)
    assert sole[flight].max() > 0.2
    # Ballistic centre of mass: constant horizontal velocity and vertical acceleration -g in flight.
    dt = 1.0 / m.fps
    com = smpl.center_of_mass(pos[clip.takeoff_frame : clip.touchdown_frame + 1])
    acc = np.diff(com, 2, axis=0) / dt**2
    np.testing.assert_allclose(acc[:, 2], -9.81, atol=0.05)
    np.testing.assert_allclose(acc[:, :2], 0.0, atol=0.05)


def test_sample_landing_is_balanced(sample_clip):
    """From touch-down on, the feet stay put and the zero-moment point of the centre of mass's path
    (x - z x'' / (g + z'')) stays between the ankles and the balls of the feet (SMPL's foot joints),
    well inside the soles: the landing brakes the flight's speed without tipping. (The first samples
    stopped the body at touch-down and restarted it, with the point 0.4 m outside the feet.)"""
    clip = sample_clip
    pos = load_human_motion(SAMPLE_PATH).joint_pos
    landed = slice(clip.touchdown_frame, None)
    feet = pos[landed][:, [7, 8, 10, 11]]
    assert np.abs(feet - feet[0]).max() < 1e-3
    dt = 1.0 / clip.fps
    com, zmp = _com_and_zmp_x(pos, dt)
    assert np.all(zmp[landed] > feet[:, :2, 0].max(axis=1))
    assert np.all(zmp[landed] < feet[:, 2:, 0].min(axis=1))
    # ... and the flight arrives fast: touch-down velocity is the flight's, not zero
    assert np.gradient(com[:, 0], dt)[clip.touchdown_frame] > 1.0


def test_sample_push_off_is_balanced(sample_clip):
    """From the bottom of the crouch to take-off the feet stay put, the zero-moment point of the centre
    of mass's path stays between the ankles and the balls of the feet, and the body speeds up forwards
    without a pause into the flight's own speed. (The sample before moved the body by the pose alone:
    it surged, then braked just before take-off with the point 0.26 m past the G1's toes, which asked
    its ankles for 2.2 times their torque.)"""
    from pipeline.human.sample import CROUCH_KEY, KEYFRAMES

    clip = sample_clip
    pos = load_human_motion(SAMPLE_PATH).joint_pos
    dt = 1.0 / clip.fps
    push = slice(int(round(KEYFRAMES[CROUCH_KEY][0] / dt)), clip.takeoff_frame + 1)
    feet = pos[push][:, [7, 8, 10, 11]]
    assert np.abs(feet - feet[0]).max() < 1e-3
    com, zmp = _com_and_zmp_x(pos, dt)
    inner = slice(push.start + 2, push.stop - 2)  # second differences across the ends mix in the neighbours
    assert np.all(zmp[inner] > feet[0, :2, 0].max())
    assert np.all(zmp[inner] < feet[0, 2:, 0].min())
    speed = np.diff(com[:, 0]) / dt
    assert np.all(np.diff(speed[push.start : clip.takeoff_frame + 1]) > 0.0)
    flight_speed = speed[clip.takeoff_frame + 1]
    assert abs(speed[clip.takeoff_frame] - flight_speed) < 0.1 * flight_speed


def test_sample_flight_keeps_its_angular_momentum(sample_clip):
    """In the air nothing outside the body can change its angular momentum about its centre of mass, so
    the sample's flight leans the whole body to keep it: constant from take-off to touch-down, while the
    arms and legs swing. (The keyed flight before swung the G1's pitch momentum between -13 and +3
    kg m^2/s.)"""
    clip = sample_clip
    pos = load_human_motion(SAMPLE_PATH).joint_pos
    momentum = smpl.angular_momentum(pos, 1.0 / clip.fps)[clip.takeoff_frame : clip.touchdown_frame]
    assert np.ptp(momentum[:, 1]) < 0.02 * np.abs(momentum[:, 1]).max()
    before = smpl.angular_momentum(pos[clip.takeoff_frame - 8 : clip.takeoff_frame + 1], 1.0 / clip.fps)[:, 1]
    assert np.ptp(before) > 0.1  # the check can fail: on the ground the momentum does change


def test_angular_momentum_of_a_spinning_body():
    """A body that only translates has none; one spinning rigidly about a horizontal axis through its
    centre of mass has its pitch inertia times the spin, where each two-joint segment is a uniform rod:
    the same as summing the rods sampled finely along their length."""
    rest = smpl.NEUTRAL_REST_JOINTS
    dt, frames = 0.01, 3
    moving = rest[None] + np.array([0.3, -0.2, 0.5]) * dt * np.arange(frames)[:, None, None]
    np.testing.assert_allclose(smpl.angular_momentum(moving, dt), 0.0, atol=1e-12)

    spin = 2.0  # rad/s about the rest pose's z (front-to-back, horizontal: the rest pose is y-up)
    com = smpl.center_of_mass(rest)
    angle = spin * dt * (np.arange(frames) - 1)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.zeros((frames, 3, 3))
    rotation[:, 0, 0], rotation[:, 0, 1], rotation[:, 1, 0], rotation[:, 1, 1], rotation[:, 2, 2] = c, -s, s, c, 1.0
    spinning = com + np.einsum("fij,nj->fni", rotation, rest - com)
    momentum = smpl.angular_momentum(spinning, dt)

    index = {name: i for i, name in enumerate(smpl.SMPL_JOINT_NAMES)}
    inertia, total = 0.0, sum(m for m, _ in smpl.SEGMENT_MASSES)
    for mass, joints in smpl.SEGMENT_MASSES:
        ends = rest[[index[j] for j in joints]]
        along = np.linspace(0.0, 1.0, 2001)[:, None]
        points = ends.mean(axis=0)[None] if len(joints) != 2 else ends[0] + along * (ends[1] - ends[0])
        inertia += mass / total * np.mean(np.sum((points[:, :2] - com[:2]) ** 2, axis=1))
    assert momentum[:, 2] == pytest.approx(inertia * spin, rel=1e-3)


def test_center_of_mass_of_the_standing_body():
    """The neutral body standing at rest: centre of mass on the mid-line, at 55-58 % of the standing
    height above the soles (the anthropometric figure for adults)."""
    rest = smpl.NEUTRAL_REST_JOINTS
    com = smpl.center_of_mass(rest[None])[0]
    assert abs(com[0]) < 0.01
    height_above_sole = (com[1] - smpl.NEUTRAL_SOLE_Y) / smpl.NEUTRAL_HEIGHT
    assert 0.53 <= height_above_sole <= 0.58
