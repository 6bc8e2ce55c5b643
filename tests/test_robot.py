"""The G1 model as AdaMimic uses it: 27 actuated joints, armature-based PD gains, 17 tracked sites."""

import math

import mujoco
import numpy as np
import pytest

from pipeline.robot.g1 import build_model, joint_dof_indices, load_robot_config, site_ids


@pytest.fixture(scope="module")
def cfg():
    return load_robot_config()


@pytest.fixture(scope="module")
def model():
    return build_model(visual=False)


def test_model_has_27_actuated_joints_with_waist_roll_pitch_locked(cfg, model):
    assert model.nu == 27 == cfg.num_joints
    assert model.njnt == 28  # free joint + 27 hinges
    names = {model.joint(i).name for i in range(model.njnt)}
    assert "waist_roll_joint" not in names and "waist_pitch_joint" not in names
    targets = [model.joint(model.actuator_trnid[a, 0]).name for a in range(model.nu)]
    assert targets == list(cfg.joint_names)


def test_pd_gains_follow_kp_j_w2_kd_2zeta_j_w(cfg, model):
    omega = 2 * math.pi * 10.0
    zeta = 2.0
    np.testing.assert_allclose(cfg.kp, cfg.armature * omega**2, rtol=1e-12)
    np.testing.assert_allclose(cfg.kd, 2 * zeta * cfg.armature * omega, rtol=1e-12)
    # The paper's worked example: J = 0.01017752 (7520-14 motor) -> Kp 40.18, Kd 2.558.
    i = cfg.joint_names.index("left_hip_pitch_joint")
    assert cfg.armature[i] == pytest.approx(0.01017752, abs=1e-8)
    assert cfg.kp[i] == pytest.approx(40.18, abs=0.005)
    assert cfg.kd[i] == pytest.approx(2.558, abs=0.0005)
    # ... and the compiled actuators carry exactly those gains, the effort limits and armature.
    np.testing.assert_allclose(model.actuator_gainprm[:, 0], cfg.kp)
    np.testing.assert_allclose(model.actuator_biasprm[:, 1], -cfg.kp)
    np.testing.assert_allclose(model.actuator_biasprm[:, 2], -cfg.kd)
    np.testing.assert_allclose(model.actuator_forcerange[:, 1], cfg.effort_limit)
    np.testing.assert_allclose(model.dof_armature[joint_dof_indices(model, cfg.joint_names)], cfg.armature)


def test_timestep_and_tracked_sites(cfg, model):
    assert model.opt.timestep == pytest.approx(0.005)
    assert cfg.decimation == 4
    assert len(cfg.tracked_body_names) == 17
    ids = site_ids(model, cfg.tracked_site_names)
    assert len(set(ids.tolist())) == 17
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_kinematics(model, data)
    head = data.site_xpos[model.site("track_head").id]
    pelvis = data.site_xpos[model.site("track_pelvis").id]
    assert head[2] > pelvis[2] + 0.3  # standing upright in the home pose
