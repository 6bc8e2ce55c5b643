"""TrackingEnv's resets: reference-state starts from stance frames and keyframes, their velocity and pose
noise, and restarts from the policy's own states."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.tracking_env import TrackingEnv
from pipeline.keyframes.tracking_data import TrackingData

from env_stand_clip import FRAMES, KEYFRAMES, N, data, hold, quiet_cfg  # noqa: F401  (data: the module fixture)


def test_reset_state_init_from_stance_frames(data):
    jump = TrackingData(**{**data.__dict__, "keyframe_labels": ("takeoff", "apex", "landing")})
    env = TrackingEnv(quiet_cfg(rsi_prob=1.0), jump, num_envs=64)
    # every frame but the flight strictly between the takeoff (10) and the landing (40), and the last
    expected = [f for f in range(FRAMES - 1) if not 10 < f < 40]
    assert env.rsi_frame_table.tolist() == expected
    torch.manual_seed(0)
    env.reset()
    frames = env.frame.numpy()
    assert set(frames.tolist()) <= set(expected) and len(set(frames.tolist())) > 10
    assert np.array_equal(env.next_kf.numpy(), np.searchsorted(KEYFRAMES, frames, side="right"))
    k = np.searchsorted(KEYFRAMES, frames, side="right") - 1  # latest keyframe at or before the start
    offsets = np.where((k >= 0)[:, None], data.keyframe_offsets[env.sample.numpy(), np.maximum(k, 0)], 0.0)
    assert np.allclose(env.backend.qpos[:, :3].numpy(), data.motion.root_pos[frames] + offsets, atol=1e-5)
    plain = TrackingEnv(quiet_cfg(rsi_prob=1.0), data, num_envs=4)  # no flight: any frame but the last
    assert plain.rsi_frame_table.tolist() == list(range(FRAMES - 1))


def test_reset_state_init_from_keyframes(data):
    env = TrackingEnv(quiet_cfg(rsi_prob=1.0, rsi_frames="keyframes"), data, num_envs=16)
    torch.manual_seed(3)
    env.reset()
    frames = env.frame.numpy()
    assert set(frames.tolist()) <= set(KEYFRAMES.tolist()) and len(set(frames.tolist())) > 1
    assert np.allclose(env.phase.numpy(), frames / (FRAMES - 1))
    k = np.searchsorted(KEYFRAMES, frames)
    assert np.array_equal(env.next_kf.numpy(), k + 1)
    sample = env.sample.numpy()
    root = data.motion.root_pos[frames] + data.keyframe_offsets[sample, k]  # latest keyframe's ψ offset
    assert np.allclose(env.backend.qpos[:, :3].numpy(), root, atol=1e-5)
    assert np.allclose(env.backend.qpos[:, 7:].numpy(), data.motion.joint_pos[frames], atol=1e-5)
    assert np.allclose(env.backend.qvel[:, 6:].numpy(), data.motion.joint_vel[frames], atol=1e-4)
    # D_edit's offsets jump at the keyframes RSI starts from: the base keeps the reference's velocity
    # (a finite difference across the jump once added ψ/(2 dt), up to 2.5 m/s here)
    assert np.allclose(env.backend.qvel[:, :3].numpy(), data.motion.root_lin_vel[frames], atol=1e-4)


def test_reset_state_velocity_noise_only_on_late_starts(data):
    """rsi_*_vel_noise perturbs the base velocity of reference-state starts within ±noise per axis;
    starts from t = 0 keep the reference's (standing) state exactly."""
    noise = {"rsi_lin_vel_noise": [0.5, 0.4, 0.2], "rsi_ang_vel_noise": [0.3, 0.3, 0.6]}
    env = TrackingEnv(quiet_cfg(rsi_prob=0.5, **noise), data, num_envs=64)
    torch.manual_seed(0)
    env.reset()
    frames = env.frame.numpy()
    late = frames > 0
    assert 10 < late.sum() < 64
    delta = env.backend.qvel[:, :6].numpy() - data.motion.qvel()[frames, :6]
    bound = np.array(noise["rsi_lin_vel_noise"] + noise["rsi_ang_vel_noise"])
    assert np.all(np.abs(delta[late]) <= bound + 1e-5)
    assert np.all(np.abs(delta[late]).max(0) > 0.6 * bound)  # spread over the whole range, every axis
    assert np.allclose(delta[~late], 0.0, atol=1e-6)
    assert np.allclose(env.backend.qvel[:, 6:].numpy(), data.motion.joint_vel[frames], atol=1e-4)
    with pytest.raises(PipelineInputError, match="rsi_lin_vel_noise"):
        quiet_cfg(rsi_lin_vel_noise=[0.5, -0.1, 0.0])
    with pytest.raises(PipelineInputError, match="rsi_ang_vel_noise"):
        quiet_cfg(rsi_ang_vel_noise=["fast", 0.0, 0.0])


def test_quat_from_rotvec_matches_the_numpy_axis_angle_and_keeps_zero_exact():
    from pipeline.common import quat
    from pipeline.envs.torch_math import quat_from_rotvec

    rotvec = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [0.0, 2.5, 0.0], [1e-9, 0.0, 0.0]])
    q = quat_from_rotvec(torch.as_tensor(rotvec)).numpy()
    assert np.array_equal(q[0], [1.0, 0.0, 0.0, 0.0])
    assert np.allclose(q, quat.from_axis_angle(rotvec), atol=1e-12)
    assert np.allclose(np.linalg.norm(q, axis=-1), 1.0)


def test_reset_pose_noise_turns_and_bends_late_starts_and_keeps_a_foot_on_the_reference_height(data):
    """rsi_root_rot_noise / rsi_joint_pos_noise perturb the pose of reference-state starts within ±noise
    (joints inside their limits); the base is then moved in z only, so that the lowest tracked foot is as
    high as the reference's. Starts from t = 0 keep the reference's state exactly, velocities are untouched."""
    from pipeline.envs.torch_math import quat_angle_sq, quat_conjugate, quat_mul

    rot, bend = [0.1, 0.2, 0.3], 0.15
    env = TrackingEnv(quiet_cfg(rsi_prob=0.5, rsi_root_rot_noise=rot, rsi_joint_pos_noise=bend), data, num_envs=64)
    torch.manual_seed(0)
    env.reset()
    frames = env.frame.numpy()
    late = frames > 0
    assert 10 < late.sum() < 64
    m = data.motion
    qpos = env.backend.qpos.numpy()
    # turned about the base's own axes: the reference's quaternion times a rotation vector within ±rot
    delta = quat_mul(quat_conjugate(torch.as_tensor(m.root_quat[frames], dtype=torch.float32)), env.backend.qpos[:, 3:7])
    turn = 2.0 * delta[:, 1:] * torch.sign(delta[:, :1])  # ≈ the rotation vector for small angles
    assert np.all(np.abs(turn.numpy()[late]) <= np.array(rot) + 2e-3)
    assert np.all(np.abs(turn.numpy()[late]).max(0) > 0.6 * np.array(rot))
    assert np.allclose(quat_angle_sq(env.backend.qpos[~late, 3:7], torch.as_tensor(m.root_quat[frames[~late]], dtype=torch.float32)).numpy(), 0.0, atol=1e-6)
    joints = qpos[:, 7:] - m.joint_pos[frames]
    assert np.all(np.abs(joints[late]) <= bend + 1e-5) and np.abs(joints[late]).max() > 0.9 * bend
    assert np.all(qpos[:, 7:] >= env.joint_pos_low.numpy() - 1e-6) and np.all(qpos[:, 7:] <= env.joint_pos_high.numpy() + 1e-6)
    assert np.allclose(joints[~late], 0.0, atol=1e-6)
    # only the height of the base moves; where it ends puts the lowest foot at the reference's height
    root = m.root_pos[frames] + env.offset_table[env.sample, env.frame].numpy()  # the ψ edit's shift
    assert np.allclose(qpos[:, :2], root[:, :2], atol=1e-5)
    assert np.allclose(qpos[~late, 2], root[~late, 2], atol=1e-5)
    assert np.abs(qpos[late, 2] - root[late, 2]).max() > 0.005
    env.backend.set_state(np.arange(64), env.backend.qpos, env.backend.qvel, forward=True)
    feet_z = env.backend.site_pos[:, env.feet_idx, 2].amin(-1).numpy()
    ref_feet_z = m.body_pos[frames][:, env.feet_idx.numpy(), 2].min(-1) + root[:, 2] - m.root_pos[frames, 2]
    assert np.allclose(feet_z, ref_feet_z, atol=1e-4)
    assert np.allclose(env.backend.qvel.numpy(), m.qvel()[frames], atol=1e-4)
    with pytest.raises(PipelineInputError, match="rsi_root_rot_noise"):
        quiet_cfg(rsi_root_rot_noise=[0.1, 0.1])
    with pytest.raises(PipelineInputError, match="rsi_joint_pos_noise"):
        quiet_cfg(rsi_joint_pos_noise=-0.1)


def test_own_state_starts_restart_where_the_policy_was(data):
    """Worlds that cross the marked keyframe alive, in episodes begun before it, are copied into the ring;
    a reset then starts from a copy: the same physics state, ψ sample, phase and observation history."""
    cfg = quiet_cfg(own_state_starts={"prob": 1.0, "at_label": "apex", "capacity": 8})
    env = TrackingEnv(cfg, data, num_envs=N)
    torch.manual_seed(0)
    env.reset()
    apex = int(KEYFRAMES[1])
    crossed_at = None
    for _ in range(apex + 5):
        obs, _, _, _, info = env.step(torch.randn(N, env.action_dim) * 0.05)
        if len(env.own_states):
            crossed_at = {"qpos": env.backend.qpos.clone(), "phase": env.phase.clone(), "sample": env.sample.clone(),
                          "actor": obs["actor"].clone(), "next_kf": env.next_kf.clone()}
            break
    assert crossed_at is not None and len(env.own_states) == N  # every world crossed the apex on the same step
    assert torch.equal(env.own_states.entries["phase"][:N], crossed_at["phase"])
    assert torch.equal(env.own_states.entries["qpos"][:N], crossed_at["qpos"])

    torch.manual_seed(1)
    obs = env.reset()  # prob 1: every world restarts from a ring entry
    entry = [int(torch.nonzero((crossed_at["qpos"] == q).all(-1))[0]) for q in env.backend.qpos]
    assert len(set(entry)) > 1  # drawn, not all the same copy
    assert torch.equal(env.phase, crossed_at["phase"][entry]) and torch.equal(env.sample, crossed_at["sample"][entry])
    assert torch.equal(obs["actor"], crossed_at["actor"][entry])
    assert torch.equal(env.next_kf, crossed_at["next_kf"][entry])
    assert (env.start_frame == apex).all() and (env.frame == apex).all()
    for _ in range(5):  # restarted at the apex they never cross it again: nothing more is recorded
        env.step(hold(env))
    assert len(env.own_states) == N

    with pytest.raises(PipelineInputError, match="at_label"):
        TrackingEnv(quiet_cfg(own_state_starts={"prob": 0.5}), data, num_envs=2)  # no keyframe labelled landing
    with pytest.raises(PipelineInputError, match="own_state_starts.prob"):
        quiet_cfg(own_state_starts={"prob": 1.5})
    from pipeline.evaluation.config import EvalConfig
    from pipeline.evaluation.evaluate import evaluation_env_config

    assert evaluation_env_config(cfg, EvalConfig()).own_state_starts.prob == 0.0  # evaluation starts at t = 0
    from pipeline.rl.config import get_variant
    from pipeline.rl.training import env_config_for

    assert env_config_for(cfg, get_variant("adamimic"), stage=2).own_state_starts.prob == 0.0  # so does stage 2
