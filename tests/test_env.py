"""TrackingEnv on the CPU backend: shapes, observations, phase, keyframe-only sparse rewards, reward values
against hand computations from the physics state, terminations and the penalty curriculum."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.envs.config import EnvConfig
from pipeline.envs.torch_math import projected_gravity, quat_angle_sq
from pipeline.envs.tracking_env import FRAME_OBS_DIM, TrackingEnv
from pipeline.keyframes.tracking_data import TrackingData

from env_stand_clip import FRAMES, KEYFRAMES, N, data, hold, quiet_cfg  # noqa: F401  (data: the module fixture)


def test_shapes_and_dtypes(data):
    env = TrackingEnv(EnvConfig(), data, num_envs=N)
    obs = env.reset()
    assert env.action_dim == 27 and env.actor_obs_dim == 5 * FRAME_OBS_DIM == 460
    assert obs["actor"].shape == (N, 460) and obs["critic"].shape == (N, env.critic_obs_dim)
    assert obs["actor"].dtype == obs["critic"].dtype == torch.float32
    assert torch.equal(obs["critic"][:, :460], obs["actor"])
    obs, rew, term, trunc, info = env.step(torch.randn(N, 27) * 0.1)
    assert rew["sparse"].shape == rew["dense"].shape == (N,) and rew["dense"].dtype == torch.float32
    assert term.dtype == trunc.dtype == torch.bool and term.shape == (N,)
    assert info["keyframe_crossed"].dtype == torch.bool
    assert info["body_pos_error_w"].shape == info["body_pos_error_local"].shape == (N, 17)
    assert info["joint_acc"].shape == (N, 27) and info["phase"].shape == info["psi"].shape == (N,)
    assert info["final_obs"]["critic"].shape == obs["critic"].shape
    layout = env.obs_layout()
    assert layout["actor_frame"]["odometry"][1] == FRAME_OBS_DIM
    assert layout["critic_privileged"]["phase_to_next_keyframe"][1] == env.critic_obs_dim
    assert all(torch.isfinite(v).all() for v in obs.values())


def test_observation_history_and_content(data):
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)
    obs0 = env.reset()
    frames0 = obs0["actor"].reshape(N, 5, FRAME_OBS_DIM)
    assert torch.equal(frames0[:, 0], frames0[:, 4])  # history filled with the first frame at reset
    action = torch.full((N, 27), 0.1)
    obs1, *_ = env.step(action)
    frames1 = obs1["actor"].reshape(N, 5, FRAME_OBS_DIM)
    assert torch.equal(frames1[:, :4], frames0[:, 1:])  # shifted by one
    new = frames1[:, 4]
    b = env.backend
    lay = env.obs_layout()["actor_frame"]
    sl = lambda k: slice(*lay[k])  # noqa: E731
    assert torch.allclose(new[:, sl("base_ang_vel")], b.qvel[:, 3:6])
    assert torch.allclose(new[:, sl("projected_gravity")], projected_gravity(b.qpos[:, 3:7]))
    assert torch.allclose(new[:, sl("joint_pos_rel")], b.qpos[:, 7:] - env.default_joint_pos)
    assert torch.allclose(new[:, sl("prev_action")], action)
    assert torch.allclose(new[:, sl("phase")].squeeze(-1), torch.full((N,), env.dphi), atol=1e-6)
    assert torch.allclose(new[:, sl("psi")].squeeze(-1), env.psi[env.sample])
    priv = obs1["critic"][:, env.actor_obs_dim:]
    assert torch.allclose(priv[:, 3:30], env.ref_joint_pos[1].expand(N, -1))


def test_odometry_refreshes_at_10hz(data):
    env = TrackingEnv(quiet_cfg(observations={"odometry_noise_std": 0.05}), data, num_envs=N)
    assert env.odom_every == 5
    env.reset()
    lay = slice(*env.obs_layout()["actor_frame"]["odometry"])
    values = []
    for _ in range(11):
        obs, *_ = env.step(hold(env))
        values.append(obs["actor"][:, -FRAME_OBS_DIM:][:, lay].clone())
    changed = [not torch.equal(values[i], values[i - 1]) for i in range(1, 11)]
    # episode steps 1..11: refreshes at steps 5 and 10 -> changes seen at list indices 4 and 9
    assert changed == [i in (4, 9) for i in range(1, 11)]


def test_phase_advance_and_adaptive_bounds(data):
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)
    env.reset()
    dphi = env.dphi
    assert math.isclose(dphi, 0.02 / ((FRAMES - 1) / 50.0))
    offsets = torch.tensor([0.0, 10.0, -10.0, 0.5 * dphi])
    *_, info = env.step(hold(env), offsets)
    expected = torch.tensor([dphi, 2 * dphi, 0.25 * dphi, 1.5 * dphi], dtype=torch.float32)
    assert torch.allclose(info["phase"], expected, atol=1e-7)
    assert torch.equal(info["frame"], torch.round(expected.double() * (FRAMES - 1)).long())


def test_sparse_rewards_only_on_keyframe_crossings(data):
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)
    env.reset()
    sparse_steps, crossed_steps = set(), set()
    for step in range(1, FRAMES):
        _, rew, term, trunc, info = env.step(hold(env))
        assert not term.any()
        nonzero = rew["sparse"] != 0
        assert torch.equal(nonzero, info["keyframe_crossed"])  # never elsewhere, always there
        assert nonzero.all() or not nonzero.any()
        if nonzero.any():
            sparse_steps.add(step)
        if info["keyframe_crossed"].any():
            crossed_steps.add(step)
            assert (info["keyframe_index"] >= 0).all()
        assert bool(trunc.all()) == (step == FRAMES - 1)
    assert sparse_steps == crossed_steps == set(KEYFRAMES.tolist())


def test_keyframe_crossing_with_fast_phase_and_sparse_values(data):
    """Doubling Δφ reaches frame 10 at step 5; the sparse reward there is the hand-computed kernel sum
    against the keyframe target of the world's ψ sample, times the semantic scale at the apex."""
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)
    env.reset()
    w, s2 = env.cfg.rewards.weights, env.cfg.rewards.sigma2
    fast = torch.full((N,), 10.0)
    hits = {}
    for step in range(1, 21):
        _, rew, _, _, info = env.step(hold(env), fast)
        if info["keyframe_crossed"].any():
            k = int(info["keyframe_index"][0])
            pos, quat = env.backend.site_pos.clone(), env.backend.site_quat.clone()
            target = torch.as_tensor(data.motion.body_pos[KEYFRAMES[k]], dtype=torch.float32)
            target = target + torch.as_tensor(data.keyframe_offsets[:, k], dtype=torch.float32)[env.sample][:, None]
            err2 = ((pos - target) ** 2).sum(-1)
            lower = torch.tensor([b in env.cfg.rewards.lower_body for b in data.motion.body_names])
            sig = torch.where(lower, torch.tensor(s2.lower_body_pos), torch.tensor(s2.upper_body_pos))
            r_pos = torch.exp(-(err2 / sig).mean(-1))
            tq = torch.as_tensor(data.motion.body_quat[KEYFRAMES[k]], dtype=torch.float32)
            r_rot = torch.exp(-quat_angle_sq(quat, tq.expand_as(quat)).mean(-1) / s2.body_rot)
            feet = [data.motion.body_names.index(f) for f in ("left_ankle", "right_ankle")]
            r_feet = torch.exp(-err2[:, feet].mean(-1) / s2.feet_pos)
            expected = data.sparse_scale[k] * (w.global_body_pos * r_pos + w.global_body_rot * r_rot
                                               + w.global_feet_pos * r_feet)
            assert torch.allclose(rew["sparse"], expected, rtol=1e-4)
            assert torch.allclose(info["keyframe_body_error_w"], err2.sqrt(), atol=1e-5)
            hits[step] = k
    assert hits == {5: 0, 13: 1, 20: 2}  # frames 10, 26 (crosses 25), 40


def test_dense_reward_terms_against_hand_values(data):
    cfg = quiet_cfg()
    cfg.rewards.weights.root_tilt, cfg.rewards.weights.root_ang_vel = 0.3, 0.2  # opt-in: off by default
    env = TrackingEnv(cfg, data, num_envs=N)
    env.reset()
    a1, a2 = torch.full((N, 27), 0.05), torch.full((N, 27), -0.05)
    env.step(a1)
    qvel_before = env.backend.qvel[:, 6:].clone()
    _, rew, _, _, info = env.step(a2)
    b, t = env.backend, info["terms"]
    frame = 2
    joint = b.qpos[:, 7:]
    ref_joint = torch.as_tensor(data.motion.joint_pos[frame], dtype=torch.float32)
    assert torch.allclose(t["local_joint_pos"], torch.exp(-((joint - ref_joint) ** 2).mean(-1)), rtol=1e-5)
    acc = (b.qvel[:, 6:] - qvel_before) / 0.02
    assert torch.allclose(t["joint_acc"], (acc**2).sum(-1), rtol=1e-4)
    assert torch.allclose(info["joint_acc"], acc, rtol=1e-4, atol=1e-3)
    assert torch.allclose(t["joint_vel"], (b.qvel[:, 6:] ** 2).sum(-1), rtol=1e-5)
    assert torch.allclose(t["action_rate"], torch.full((N,), 27 * 0.1**2), rtol=1e-5)
    assert torch.allclose(t["smoothness"], torch.full((N,), 27 * (-0.05 - 0.1) ** 2), rtol=1e-5)  # a2-2a1+0
    assert torch.allclose(t["torques"], (b.actuator_force**2).sum(-1), rtol=1e-5)
    # root terms: pelvis tilt and body-frame angular velocity against the reference's at the frame
    s2 = env.cfg.rewards.sigma2
    ref_root_quat = torch.as_tensor(data.motion.root_quat[frame], dtype=torch.float32).expand(N, 4)
    tilt2 = ((projected_gravity(b.qpos[:, 3:7]) - projected_gravity(ref_root_quat))[:, :2] ** 2).sum(-1)
    assert tilt2.max() > 1e-8  # the step moved the pelvis off the reference's tilt: the kernel is tested below 1
    assert torch.allclose(t["root_tilt"], torch.exp(-tilt2 / s2.root_tilt), rtol=1e-5)
    ref_ang_vel = torch.as_tensor(data.motion.qvel()[frame, 3:6], dtype=torch.float32)
    ang2 = ((b.qvel[:, 3:6] - ref_ang_vel) ** 2).sum(-1)
    assert torch.allclose(t["root_ang_vel"], torch.exp(-ang2 / s2.root_ang_vel), rtol=1e-5)
    w = env.cfg.rewards.weights
    total = sum(getattr(w, k) * v for k, v in t.items())
    assert torch.allclose(rew["dense"], total)
    # local body position: root-frame positions against the reference's, with per-body σ²
    root_pos, root_quat = b.qpos[:, :3], b.qpos[:, 3:7]
    from pipeline.common import quat as npq

    local = npq.inverse_rotate(root_quat[:, None].double().numpy(), (b.site_pos - root_pos[:, None]).double().numpy())
    ref_local = npq.inverse_rotate(data.motion.root_quat[frame], data.motion.body_pos[frame] - data.motion.root_pos[frame])
    err2 = ((local - ref_local) ** 2).sum(-1)
    inv = np.array([1 / 0.1 if n in env.cfg.rewards.lower_body else 1 / 0.03 for n in data.motion.body_names])
    assert np.allclose(t["local_body_pos"].numpy(), np.exp(-(err2 * inv).mean(-1)), rtol=1e-4)
    assert torch.allclose(info["body_pos_error_local"] ** 2, torch.as_tensor(err2, dtype=torch.float32), atol=1e-5)


def test_terminations(data):
    # timeout: truncated, not terminated, at the motion's end (checked in the crossing test too)
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)
    env.reset()
    # tilt: a robot lying on its side (projected gravity xy = 1)
    qpos = env.backend.qpos.clone()
    qpos[0, 3:7] = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    qpos[0, 2] = 1.0
    env.backend.set_state(torch.tensor([0]), qpos[:1], env.backend.qvel[:1].clone())
    _, rew, term, trunc, _ = env.step(hold(env))
    assert term.tolist() == [True, False, False, False] and not trunc.any()
    assert rew["sparse"][0] == pytest.approx(-200.0) and (rew["sparse"][1:] == 0).all()
    assert env.phase[0] == 0  # auto-reset

    # base height (absolute): the threshold above a standing robot terminates everyone, unless the task is exempt
    absolute = {"min_base_height": 2.0, "relative_to_reference": False}
    env = TrackingEnv(quiet_cfg(terminations=absolute), data, num_envs=N)
    env.reset()
    assert env.step(hold(env))[2].all()
    env = TrackingEnv(quiet_cfg(terminations={**absolute, "base_height_exempt_tasks": ["stand"]}), data, num_envs=N)
    env.reset()
    assert not env.step(hold(env))[2].any()


def test_fall_terminations_follow_the_reference(data):
    # height: z < min(min_base_height, z_ref − margin); the standing reference (0.76 m) gives 0.51 m
    env = TrackingEnv(quiet_cfg(terminations={"min_base_height": 2.0, "base_height_margin": 0.25}), data, num_envs=N)
    env.reset()
    _, _, term, _, info = env.step(hold(env))
    assert not term.any() and not info["terminated_by"]["base_height"].any()
    env.ref_root_pos[:, 2] += 1.0  # a reference 1 m higher: 1.51 m, above the robot
    _, rew, term, _, info = env.step(hold(env))
    assert term.all() and info["terminated_by"]["base_height"].all() and (rew["sparse"] == -200.0).all()

    # tilt: |g_xy(robot) − g_xy(reference)| > 0.8
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)
    env.reset()
    env.ref_gravity_xy[:] = torch.tensor([0.75, 0.0])  # the reference leans (as the far-jump crouch does)
    _, _, term, _, info = env.step(hold(env))
    assert not term.any()  # an upright robot is 0.75 from it: within 0.8
    env.ref_gravity_xy[:] = torch.tensor([0.9, 0.0])
    _, _, term, _, info = env.step(hold(env))
    assert term.all() and info["terminated_by"]["tilt"].all()
    env = TrackingEnv(quiet_cfg(terminations={"relative_to_reference": False}), data, num_envs=N)
    env.reset()
    env.ref_gravity_xy[:] = torch.tensor([0.9, 0.0])  # ignored by the absolute check
    assert not env.step(hold(env))[2].any()


def test_keyframe_error_termination_and_curriculum(data):
    far = TrackingData(**{**data.__dict__, "keyframe_offsets": data.keyframe_offsets + np.array([0.0, 0.0, 1.0])})
    env = TrackingEnv(quiet_cfg(), far, num_envs=N)
    assert env.termination_threshold == 1.5
    assert env.update_curriculum(0.0) == 1.5
    assert env.update_curriculum(0.25) == pytest.approx(1.05)
    assert env.update_curriculum(0.5) == pytest.approx(0.6)
    assert env.update_curriculum(0.7) == pytest.approx(0.6)
    assert env.update_curriculum(1.0) == pytest.approx(2.0)
    assert env.set_termination_threshold(0.1) == 0.6 and env.set_termination_threshold(5.0) == 2.0
    env.set_termination_threshold(0.6)  # keyframes sit 1 m above the robot: the first crossing fails
    env.reset()
    for step in range(1, KEYFRAMES[0] + 1):
        _, rew, term, _, info = env.step(hold(env))
        assert bool(term.any()) == (step == KEYFRAMES[0])
    assert term.all() and info["keyframe_crossed"].all()
    assert (rew["sparse"] < -190).all()  # −200 plus the (small) keyframe tracking reward
    env.set_termination_threshold(2.0)  # 1 m error passes at the loosest threshold
    env.reset()
    for _ in range(KEYFRAMES[0]):
        term = env.step(hold(env))[2]
    assert not term.any()


def test_keyframe_error_measure_max_or_mean(data):
    """One body's keyframe target 1 m off, the others exact: past 0.6 m for the worst body, about
    1/17 m for the bodies' mean."""
    offsets = np.repeat(data.keyframe_offsets[:, :, None, :], len(data.motion.body_names), axis=2)
    offsets[:, :, data.motion.body_names.index("head"), 2] += 1.0
    target = data.motion.body_pos[data.keyframe_frames][None] + offsets
    ends = {}
    for measure in ("max", "mean"):
        env = TrackingEnv(quiet_cfg(terminations={"keyframe_error": {"measure": measure}}), data, num_envs=N)
        env.kf_target_pos = torch.as_tensor(target, dtype=env.kf_target_pos.dtype)
        env.set_termination_threshold(0.6)
        env.reset()
        for _ in range(KEYFRAMES[0]):
            _, _, term, _, info = env.step(hold(env))
        assert info["keyframe_crossed"].all()
        ends[measure] = bool(term.all()), bool(info["terminated_by"]["keyframe_error"].any())
    assert ends == {"max": (True, True), "mean": (False, False)}


def test_penalty_curriculum_follows_the_fall_rate(data):
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)
    assert env.penalty_scale == 1.0  # outside training: the paper's weights
    env.update_curriculum(0.0)
    assert env.penalty_scale == pytest.approx(0.1)  # training starts light
    env.update_curriculum(0.5)
    assert env.penalty_scale == pytest.approx(0.1)  # no episode finished since: unchanged
    env.episodes_finished, env.episodes_terminated = 10, 1  # 10 % fell: penalties grow by 5 %
    env.update_curriculum(0.5)
    assert env.penalty_scale == pytest.approx(0.105)
    assert env.episodes_finished == env.episodes_terminated == 0  # counted afresh for the next update
    env.episodes_finished, env.episodes_terminated = 10, 4  # 40 %: between the levels, held
    env.update_curriculum(0.5)
    assert env.penalty_scale == pytest.approx(0.105)
    env.episodes_finished, env.episodes_terminated = 10, 9  # 90 %: shrinks, but not below `initial`
    env.update_curriculum(0.5)
    assert env.penalty_scale == pytest.approx(0.1)
    for _ in range(100):
        env.episodes_finished, env.episodes_terminated = 10, 0
        env.update_curriculum(0.5)
    assert env.penalty_scale == pytest.approx(1.0)  # capped at the paper's weights
    # the env counts its own finished and terminated episodes
    env.set_termination_threshold(2.0)
    env.reset()
    for _ in range(3):
        env.step(torch.full((N, 27), 0.3))
    env.backend.set_state(torch.arange(N), *_fallen_state(env))
    _, _, term, trunc, _ = env.step(hold(env))
    assert term.all() and env.episodes_finished == N and env.episodes_terminated == N


def _fallen_state(env):
    qpos, qvel = env.backend.qpos.clone(), env.backend.qvel.clone()
    qpos[:, 2] = 0.1  # pelvis on the floor
    return qpos, qvel


def test_penalty_scale_scales_only_the_penalties(data):
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)
    w = env.cfg.rewards.weights
    for scale in (0.1, 1.0):
        env.penalty_scale = scale
        env.reset()
        _, rew, _, _, info = env.step(torch.full((N, 27), 0.3))
        t = info["terms"]
        positive = sum(getattr(w, k) * t[k] for k in t if getattr(w, k) > 0)
        negative = sum(getattr(w, k) * t[k] for k in t if getattr(w, k) < 0)
        assert torch.allclose(rew["dense"], positive + env.penalty_scale * negative, rtol=1e-5, atol=1e-5)
        assert (negative < -0.5).all()  # the action-rate jump from rest is a real penalty
