"""The left-right mirror of the G1 (train.fast_td3.mirror): an involution, mirrored poses with mirrored bodies,
mirrored motions under the dynamics, and TrackingEnv's observation of a mirrored state."""

from __future__ import annotations

import types

import mujoco
import numpy as np
import torch

from pipeline.rl.mirror import Mirror, joint_mirror, qpos_mirror

from env_stand_clip import data  # noqa: F401  (the module fixture: a 61-frame standing clip, 3 keyframes)


def g1():
    from pipeline.robot.g1 import build_model, load_robot_config

    return build_model(), load_robot_config()


def tracking_layout(num_joints: int, history: int = 5) -> tuple[dict, int, int]:
    """TrackingEnv's own obs_layout, computed by its method on a stand-in with its sizes."""
    from pipeline.envs.tracking_env import FRAME_OBS_DIM, TrackingEnv

    actor_dim = FRAME_OBS_DIM * history
    stand_in = types.SimpleNamespace(num_joints=num_joints, actor_obs_dim=actor_dim,
                                     cfg=types.SimpleNamespace(observations=types.SimpleNamespace(history=history)))
    layout = TrackingEnv.obs_layout(stand_in)
    return layout, actor_dim, actor_dim + 3 + num_joints + 1 + 1


def test_mirror_of_the_mirror_is_exactly_the_identity():
    _, robot = g1()
    layout, actor_dim, critic_dim = tracking_layout(len(robot.joint_names))
    mirror = Mirror.from_layout(layout, robot.joint_names, actor_dim, critic_dim, len(robot.joint_names) + 1)
    torch.manual_seed(0)
    for kind, dim in (("actor", actor_dim), ("critic", critic_dim), ("raw", len(robot.joint_names) + 1)):
        x = torch.randn(32, dim)
        once = mirror.apply(kind, x)
        assert not torch.equal(once, x)
        assert torch.equal(mirror.apply(kind, once), x), kind
    # the phase, ψ and the phase-rate offset stay; gravity's y and the angular velocity's x flip
    frame = layout["actor_frame"]
    x = torch.randn(1, critic_dim)
    m = mirror.critic(x)
    for name in ("phase", "psi"):
        assert torch.equal(m[0, frame[name][0]], x[0, frame[name][0]])
    g0 = frame["projected_gravity"][0]
    assert torch.equal(m[0, g0 : g0 + 3], x[0, g0 : g0 + 3] * torch.tensor([1.0, -1.0, 1.0]))
    w0 = frame["base_ang_vel"][0]
    assert torch.equal(m[0, w0 : w0 + 3], x[0, w0 : w0 + 3] * torch.tensor([-1.0, 1.0, -1.0]))
    raw = torch.randn(1, len(robot.joint_names) + 1)
    assert torch.equal(mirror.raw(raw)[0, -1], raw[0, -1])
    # the default pose is its own mirror (joint_pos_rel is measured from it)
    default = torch.as_tensor(robot.default_joint_pos, dtype=torch.float32)
    partner, sign = joint_mirror(robot.joint_names)
    assert torch.equal(default[partner] * sign, default)


def _partner_body(name: str) -> str:
    return name.replace("left_", "\0").replace("right_", "left_").replace("\0", "right_")


def test_mirrored_pose_has_mirrored_body_positions_and_orientations():
    """Forward kinematics of the G1: the mirrored pose puts each body where its partner was, y flipped,
    turned by M R M. This checks the joint pairing and which joints change sign."""
    model, robot = g1()
    data, mirrored_data = mujoco.MjData(model), mujoco.MjData(model)
    rng = np.random.default_rng(0)
    lo, hi = model.jnt_range[1:, 0], model.jnt_range[1:, 1]
    M = np.diag([1.0, -1.0, 1.0])
    for _ in range(5):
        qpos = np.zeros(model.nq)
        qpos[:3] = rng.normal(size=3)
        quat = rng.normal(size=4)
        qpos[3:7] = quat / np.linalg.norm(quat)
        qpos[7:] = rng.uniform(np.maximum(lo, -1.0), np.minimum(hi, 1.0))
        data.qpos[:] = qpos
        mirrored_data.qpos[:] = qpos_mirror(torch.as_tensor(qpos), robot.joint_names).numpy()
        mujoco.mj_kinematics(model, data)
        mujoco.mj_kinematics(model, mirrored_data)
        for b in range(1, model.nbody):
            partner = model.body(_partner_body(model.body(b).name)).id
            np.testing.assert_allclose(mirrored_data.xpos[partner], M @ data.xpos[b], atol=2e-3,
                                       err_msg=model.body(b).name)
            rot = data.xmat[b].reshape(3, 3)
            np.testing.assert_allclose(mirrored_data.xmat[partner].reshape(3, 3), M @ rot @ M, atol=2e-2,
                                       err_msg=model.body(b).name)


def test_mirrored_motion_stays_mirrored_under_the_dynamics():
    """In flight (no contact), a mirrored state with mirrored joint torques evolves into the mirror of
    the original's state: the mirror of qvel (base angular velocity axial, joints paired with signs) is right."""
    model, robot = g1()
    rng = np.random.default_rng(1)
    data, mirrored = mujoco.MjData(model), mujoco.MjData(model)
    qpos = np.zeros(model.nq)
    qpos[:3] = [0.0, 0.0, 3.0]
    qpos[3] = 1.0
    qpos[7:] = robot.default_joint_pos
    qvel = rng.normal(scale=0.5, size=model.nv)
    ctrl = rng.normal(scale=5.0, size=model.nu)
    partner, sign = (t.numpy() for t in joint_mirror(robot.joint_names))
    actuated = [model.joint(model.actuator_trnid[a, 0]).name for a in range(model.nu)]
    assert actuated == list(robot.joint_names)

    def mirror_vel(v):
        out = v.copy()
        out[:3] = v[:3] * [1.0, -1.0, 1.0]        # base linear velocity (world frame): polar
        out[3:6] = v[3:6] * [-1.0, 1.0, -1.0]     # base angular velocity: axial
        out[6:] = sign * v[6:][partner]
        return out

    data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, qvel, ctrl
    mirrored.qpos[:] = qpos_mirror(torch.as_tensor(qpos), robot.joint_names).numpy()
    mirrored.qvel[:], mirrored.ctrl[:] = mirror_vel(qvel), sign * ctrl[partner]
    for _ in range(20):
        mujoco.mj_step(model, data)
        mujoco.mj_step(model, mirrored)
    assert data.ncon == 0
    # The G1's model is near symmetric, not exactly (its links' inertias differ in the last digits): the
    # mirror agrees to under 2 % of the motion's size; a wrong pairing or sign would be off by the size itself.
    want_qpos = qpos_mirror(torch.as_tensor(data.qpos.copy()), robot.joint_names).numpy()
    moved = np.abs(data.qpos - qpos).max()
    assert np.abs(mirrored.qpos - want_qpos).max() < 0.02 * moved
    want_qvel = mirror_vel(data.qvel.copy())
    assert np.abs(mirrored.qvel - want_qvel).max() < 0.02 * np.abs(data.qvel).max()
    # and the check can fail: the mirror without the roll/yaw sign flips is far off
    unsigned = want_qvel.copy()
    unsigned[6:] = data.qvel[6:][partner]
    assert np.abs(mirrored.qvel - unsigned).max() > 0.2 * np.abs(data.qvel).max()


def test_the_observation_of_a_mirrored_state_is_the_mirror_of_the_observation(data):  # noqa: F811
    """TrackingEnv's own observation code on a physics state and on its mirror image: the actor
    observation and the critic's base velocity agree with Mirror's map of the original's."""
    from pipeline.envs.config import EnvConfig
    from pipeline.envs.tracking_env import TrackingEnv
    from pipeline.rl.mirror import mirror_for_env

    torch.manual_seed(0)
    env = TrackingEnv(EnvConfig.from_dict({"observations": {"odometry_noise_std": 0.0}}), data, num_envs=2)
    env.reset()
    names = env.robot.joint_names
    partner, sign = joint_mirror(names)
    qpos = env.backend.qpos[0].clone().double()
    qpos[:3] += torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    turn = torch.tensor([0.9, 0.1, -0.2, 0.3], dtype=torch.float64)
    qpos[3:7] = turn / turn.norm()
    qpos[7:] += 0.2 * torch.randn(len(names), dtype=torch.float64)
    qvel = torch.randn(env.backend.qvel.shape[1], dtype=torch.float64)
    mirrored_qvel = qvel.clone()
    mirrored_qvel[:3] = qvel[:3] * torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)   # world linear: polar
    mirrored_qvel[3:6] = qvel[3:6] * torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64)  # body angular: axial
    mirrored_qvel[6:] = sign.double() * qvel[6:][partner]
    env.backend.set_state(torch.arange(2), torch.stack([qpos, qpos_mirror(qpos, names)]).to(env.backend.qpos.dtype),
                          torch.stack([qvel, mirrored_qvel]).to(env.backend.qvel.dtype))
    action = torch.randn(len(names))
    env.prev_action = torch.stack([action, sign * action[partner]]).to(env.prev_action.dtype)
    env.episode_step.zero_()
    env.odom_origin.zero_()
    env.odom_origin_quat[:] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    env.sample[:] = env.sample[0]
    env.phase[:] = env.phase[0]
    frame_obs, privileged, _ = env._frame_features(None)
    mirror = mirror_for_env(env, env.action_dim)
    frame_dim = frame_obs.shape[1]
    actor = frame_obs.repeat(1, env.cfg.observations.history)  # every history slot: this frame
    want = mirror.actor(actor[:1])[0, -frame_dim:]
    assert torch.allclose(frame_obs[1], want, atol=1e-4), (frame_obs[1] - want).abs().max()
    layout = env.obs_layout()["critic_privileged"]
    critic = torch.cat([actor, privileged], -1)
    start, stop = layout["base_lin_vel"]
    assert torch.allclose(critic[1, start:stop], mirror.critic(critic[:1])[0, start:stop], atol=1e-4)
