"""TrackingEnv on the CPU backend: shapes, phase, keyframe-only sparse rewards, reward values against
hand computations from the physics state, terminations, reset/RSI, domain randomisation, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import EnvConfig
from pipeline.envs.torch_math import projected_gravity, quat_angle_sq
from pipeline.envs.tracking_env import FRAME_OBS_DIM, TrackingEnv
from pipeline.keyframes.tracking_data import TrackingData
from pipeline.motion.motion import RobotKinematics

FRAMES = 61  # 1.2 s at 50 fps
KEYFRAMES = np.array([10, 25, 40])
N = 4


@pytest.fixture(scope="module")
def data() -> TrackingData:
    kin = RobotKinematics()
    rc = kin.config
    t = np.arange(FRAMES) / 50.0
    joints = np.tile(rc.default_joint_pos, (FRAMES, 1))
    joints[:, rc.joint_names.index("left_elbow_joint")] += 0.3 * np.sin(2 * np.pi * t)
    root = np.tile([0.0, 0.0, rc.default_root_height], (FRAMES, 1))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (FRAMES, 1))
    motion = kin.motion(50.0, root, quat, joints, name="stand")
    psi = np.array([0.0, 0.05, 0.1])
    offsets = np.zeros((3, len(KEYFRAMES), 3))
    offsets[:, :, 0] = psi[:, None]  # keyframe targets moved forward by ψ
    return TrackingData(task="stand", motion=motion, keyframe_frames=KEYFRAMES, keyframe_labels=("", "apex", ""),
                        sparse_scale=np.array([1.0, 50.0, 1.0]), edited=np.ones(3, bool), psi=psi,
                        keyframe_offsets=offsets)


def quiet_cfg(**extra) -> EnvConfig:
    """No randomisation, no RSI, no odometry noise: a standing robot tracks the clip to the end. ψ drawn
    uniformly, so the worlds track different samples from the first reset (a curriculum starts them all
    at the sample nearest ψ_raw)."""
    raw = {"randomization": {"enabled": False}, "rsi_prob": 0.0, "observations": {"odometry_noise_std": 0.0},
           "sampling": {"mode": "uniform"}}
    for key, value in extra.items():
        raw[key] = {**raw.get(key, {}), **value} if isinstance(value, dict) else value
    return EnvConfig.from_dict(raw)


def hold(env) -> torch.Tensor:
    return torch.zeros(env.num_envs, env.action_dim)


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


def test_domain_randomisation_ranges_applied(data):
    n = 32
    env = TrackingEnv(EnvConfig(), data, num_envs=n)
    env.reset()
    b, m, ids = env.backend, env.model, np.arange(n)
    trunk, base = m.body("torso_link").id, m.body("pelvis").id
    mass = b.get_model_field("body_mass", ids)
    added = mass[:, trunk] - m.body_mass[trunk]
    assert added.min() >= -2.0 and added.max() <= 5.0 and added.std() > 0.5
    others = [i for i in range(1, m.nbody) if i != trunk]
    ratio = mass[:, others] / m.body_mass[others]
    assert ratio.min() >= 0.9 and ratio.max() <= 1.1 and ratio.std() > 0.01
    inertia = b.get_model_field("body_inertia", ids)
    assert np.allclose(inertia[:, others] / m.body_inertia[others], ratio[..., None])
    com = b.get_model_field("body_ipos", ids)[:, base] - m.body_ipos[base]
    assert np.abs(com).max() <= 0.1 and com.std() > 0.01
    # U(0.1, 1.1) averaged with the ground's 1.0 as PhysX combines materials: contacts in [0.55, 1.05]
    friction = b.get_model_field("geom_friction", ids)[:, m.geom_bodyid > 0, 0]
    assert friction.min() >= 0.55 and friction.max() <= 1.05 and friction.std() > 0.05
    robot = TrackingEnv(EnvConfig.from_dict({"randomization": {"friction_combine": "robot"}}), data, num_envs=n)
    robot.reset()
    friction = robot.backend.get_model_field("geom_friction", ids)[:, m.geom_bodyid > 0, 0]
    assert friction.min() >= 0.1 and friction.max() <= 1.1 and friction.min() < 0.5
    feet = np.flatnonzero((m.geom_priority > 0) & (m.geom_bodyid > 0))
    damp = b.get_model_field("geom_solref", ids)[:, feet, 1]
    assert damp.min() >= 0.59 and damp.max() <= 1.0  # restitution 0.1 <-> ζ ≈ 0.59
    kp = b.get_model_field("actuator_gainprm", ids)[..., 0] / m.actuator_gainprm[:, 0]
    kd = b.get_model_field("actuator_biasprm", ids)[..., 2] / m.actuator_biasprm[:, 2]
    assert kp.min() >= 0.85 * 0.9 and kp.max() <= 1.15 * 1.1 and kp.std() > 0.02
    assert kd.min() >= 0.85 * 0.9 and kd.max() <= 1.15 * 1.1
    bias_p = b.get_model_field("actuator_biasprm", ids)[..., 1] / m.actuator_biasprm[:, 1]
    assert np.allclose(bias_p, kp)  # position actuator stays a PD about the target
    delay = env.delay_substeps.numpy()
    assert delay.min() >= 0 and delay.max() <= 20 and len(set(delay.tolist())) > 3
    lag = env.delay_lag.numpy()
    sub = np.arange(4)
    assert np.array_equal(lag, np.maximum(0, np.ceil((delay[:, None] - sub) / 4)).astype(int))


def test_randomisation_terms_switch_off(data):
    cfg = EnvConfig.from_dict({"randomization": {"friction": {"enabled": False}, "p_gain_scale": {"enabled": False},
                                                 "motor_strength": {"enabled": False},
                                                 "control_delay_ms": {"enabled": False}}})
    env = TrackingEnv(cfg, data, num_envs=8)
    env.reset()
    ids, m = np.arange(8), env.model
    assert np.array_equal(env.backend.get_model_field("geom_friction", ids), np.repeat(m.geom_friction[None], 8, 0))
    assert np.allclose(env.backend.get_model_field("actuator_gainprm", ids)[..., 0], m.actuator_gainprm[:, 0])
    kd = env.backend.get_model_field("actuator_biasprm", ids)[..., 2] / m.actuator_biasprm[:, 2]
    assert kd.std() > 0.01  # D gains still randomised
    assert not env.randomizer.delay_enabled and (env.delay_lag == 0).all()


def test_control_delay_feeds_old_targets(data):
    """A 10 ms delay (2 substeps) applies the previous step's target on substeps 0-1 of each step."""
    cfg = quiet_cfg(randomization={"enabled": True, "trunk_mass_add": {"enabled": False},
                                   "base_com_offset": {"enabled": False}, "link_mass_scale": {"enabled": False},
                                   "friction": {"enabled": False}, "restitution": {"enabled": False},
                                   "p_gain_scale": {"enabled": False}, "d_gain_scale": {"enabled": False},
                                   "motor_strength": {"enabled": False}, "push": {"enabled": False},
                                   "control_delay_ms": {"low": 10.0, "high": 10.0}})
    env = TrackingEnv(cfg, data, num_envs=2)
    env.reset()
    assert env.delay_lag.tolist() == [[1, 1, 0, 0]] * 2
    first = env.default_joint_pos + env.action_scale * 0.2
    ctrl = env._delayed_control(first.expand(2, -1))
    assert torch.allclose(ctrl[:, 2:], first.expand(2, 2, -1))
    assert torch.allclose(ctrl[:, :2], env.ref_joint_pos[0].expand(2, 2, -1))


def test_action_offset_default_reference_or_feedforward(data, monkeypatch):
    """Joint targets = offset + scale·a: the default pose, or the reference's joints at the frame the
    step ends on (after the adaptive phase), so a zero action replays the reference's joints, or those
    plus the PD feedforward (envs/feedforward.py)."""
    from pipeline.envs.feedforward import feedforward_joint_targets

    targets = []
    for offset in ("default", "reference", "feedforward"):
        env = TrackingEnv(quiet_cfg(action_offset=offset), data, num_envs=2)
        env.reset()
        sent = []
        delayed = env._delayed_control
        monkeypatch.setattr(env, "_delayed_control", lambda t, sent=sent, delayed=delayed: sent.append(t.clone()) or delayed(t))
        action = torch.full((2, env.action_dim), 0.1)
        for _ in range(3):
            env.step(action, phase_rate_offset=torch.tensor([0.0, env.dphi]))  # world 1 runs at twice the rate
        targets.append(sent[-1])
        assert env.frame.tolist() == [3, 6]
    assert torch.allclose(targets[0], (env.default_joint_pos + env.action_scale * 0.1).expand(2, -1))
    assert torch.allclose(targets[1], env.ref_joint_pos[torch.tensor([3, 6])] + env.action_scale * 0.1)
    assert not torch.allclose(targets[1][0], targets[1][1])  # the elbow waves: frames 3 and 6 differ
    feedforward = torch.as_tensor(feedforward_joint_targets(data.motion), dtype=torch.float32)
    assert torch.allclose(targets[2], feedforward[torch.tensor([3, 6])] + env.action_scale * 0.1, atol=1e-5)


def test_bad_input(data, monkeypatch):
    with pytest.raises(PipelineInputError, match="num_envs"):
        TrackingEnv(EnvConfig(), data, num_envs=0)
    with pytest.raises(PipelineInputError, match="num_envs"):
        TrackingEnv(EnvConfig(), data, num_envs=-3)
    with pytest.raises(PipelineInputError, match="backend"):
        TrackingEnv(EnvConfig(), data, num_envs=2, backend="physx")
    m = data.motion
    wrong = TrackingData(**{**data.__dict__, "motion": type(m)(**{
        **{k: getattr(m, k) for k in ("fps", "body_names", "root_pos", "root_quat", "body_pos", "body_quat")},
        "joint_names": m.joint_names[:-1] + ("tail_joint",), "joint_pos": m.joint_pos})})
    with pytest.raises(PipelineInputError, match="joint_names"):
        TrackingEnv(EnvConfig(), wrong, num_envs=2)

    import pipeline.keyframes.terrain as terrain

    def broken_builder(task):
        raise ValueError("gap wider than the world")

    monkeypatch.setattr(terrain, "terrain_builder", broken_builder)
    monkeypatch.setattr(terrain, "terrain_layout", lambda task, psi: {})
    gap = TrackingData(**{**data.__dict__, "terrain": {"kind": "gap"}})
    with pytest.raises(PipelineInputError, match="terrain"):
        TrackingEnv(EnvConfig(), gap, num_envs=2)


def test_terrain_per_world_follows_psi(data):
    """A step whose height is ψ (keyframes' terrain): each world's box top matches its ψ sample."""
    step = TrackingData(**{**data.__dict__, "terrain": {
        "kind": "step", "height": "psi", "anchors": {"psi_raw": 0.0, "steps": [{"edge": 0.5}]}}})
    env = TrackingEnv(quiet_cfg(), step, num_envs=8)
    torch.manual_seed(1)
    env.reset()
    box = env.model.geom("terrain_box_1").id
    pos = env.backend.get_model_field("geom_pos", np.arange(8))[:, box]
    psi = data.psi[env.sample.numpy()]
    assert len(set(psi.tolist())) > 1
    assert np.allclose(pos[:, 2] + env.model.geom_size[box, 2], psi)  # box top = ψ
    _, _, term, _, _ = env.step(hold(env))
    assert not term.any()


def test_dense_tracking_variant(data):
    env = TrackingEnv(quiet_cfg(variant={"tracking": "dense"}), data, num_envs=N)
    env.reset()
    for step in range(1, KEYFRAMES[0] + 1):
        _, rew, term, _, info = env.step(hold(env))
        assert (rew["sparse"] == 0).all() and not term.any()  # no keyframe payments in the dense variant
        assert (rew["dense"] > sum(getattr(env.cfg.rewards.weights, k) * v for k, v in info["terms"].items()) + 5).all()
    assert info["keyframe_crossed"].all()  # crossings still reported for evaluation


def test_compiled_step_matches_the_eager_step(data, monkeypatch):
    """`env.compile` fuses the step's rewards, terminations and observations: same episodes as eager
    (randomisation, resets and keyframe terminations included), and the curricula's changes of the
    threshold and penalty scale reach the compiled step without compiling it again."""
    import torch._dynamo

    far = TrackingData(**{**data.__dict__, "keyframe_offsets": data.keyframe_offsets + np.array([0.0, 0.0, 1.0])})
    runs = {}
    for compiled in (False, True):
        torch.manual_seed(0)
        env = TrackingEnv(EnvConfig.from_dict({"compile": compiled}), far, num_envs=N)
        env.reset()
        gen = torch.Generator().manual_seed(1)
        steps = []
        for i in range(75):  # the clip's 60 steps and a second episode
            if i == 5:
                env.set_termination_threshold(0.6)  # the 1 m high keyframe targets now end episodes
                env.penalty_scale = 0.3
                torch._dynamo.reset()  # any later compilation is a recompilation
                monkeypatch.setattr(torch._dynamo.config, "error_on_recompile", compiled)
            if i == 40:
                env.set_termination_threshold(0.7)
                env.penalty_scale = 0.6
            obs, rew, term, trunc, info = env.step(0.5 * torch.randn(N, env.action_dim, generator=gen))
            steps.append((obs["critic"], rew["sparse"], rew["dense"], term, trunc, info["keyframe_crossed"],
                          info["terminated_by"]["keyframe_error"], info["body_pos_error_local"]))
        runs[compiled] = steps
    assert sum(int(s[6].sum()) for s in runs[False]) > 0  # some episodes ended at a keyframe
    for eager, fused in zip(runs[False], runs[True]):
        for a, b in zip(eager, fused):
            if a.dtype == torch.bool:
                assert torch.equal(a, b)
            else:
                torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


def test_pushes_kick_the_base(data):
    cfg = quiet_cfg(randomization={"enabled": True, "push": {"interval_s": [0.02, 0.02], "max_vel_xy": 1.0}})
    env = TrackingEnv(cfg, data, num_envs=N)
    torch.manual_seed(0)
    env.reset()
    before = env.backend.qvel[:, :2].clone()
    env._apply_pushes()
    kick = env.backend.qvel[:, :2] - before
    assert (kick.abs() <= 1.0 + 1e-6).all() and kick.abs().sum() > 0.1


def test_feedforward_holds_the_reference_where_the_bare_reference_sags(data):
    """A zero action around the bare reference joints lets gravity bend the G1 away from a standing
    clip (the soft PD gains need an error to push back); with the inverse-dynamics feedforward the
    actuators already apply the holding torques, and the joints stay on the reference."""
    error = {}
    for offset in ("reference", "feedforward"):
        env = TrackingEnv(quiet_cfg(action_offset=offset), data, num_envs=1)
        env.reset()
        worst = 0.0
        for _ in range(40):
            env.step(hold(env))
            worst = max(worst, float((env.backend.qpos[0, 7:] - env.ref_joint_pos[env.frame[0]]).abs().max()))
        error[offset] = worst
    assert error["feedforward"] < 0.25 * error["reference"], error
    assert error["feedforward"] < 0.05, error  # measured: 0.25 rad around the bare reference, 0.034 with it


def test_psi_scale_samples_pins_the_psi_input_at_the_samples_spread(data):
    from pipeline.rl.networks import EmpiricalNormalizer
    from pipeline.rl.training import pin_observation_stats

    running = TrackingEnv(quiet_cfg(observations={"psi_scale": "running"}), data, num_envs=N)
    assert running.pinned_observation_stats() == []
    env = TrackingEnv(quiet_cfg(), data, num_envs=N)  # "samples", the default
    [(columns, mean, var)] = env.pinned_observation_stats()
    start = env.obs_layout()["actor_frame"]["psi"][0]
    assert columns == [h * FRAME_OBS_DIM + start for h in range(5)]
    assert mean == pytest.approx(float(np.mean(data.psi))) and var == pytest.approx(float(np.var(data.psi)))
    obs = env.reset()
    for column in columns:
        assert torch.allclose(obs["actor"][:, column], env.psi[env.sample])
    actor, critic = EmpiricalNormalizer(env.actor_obs_dim), EmpiricalNormalizer(env.critic_obs_dim)
    pin_observation_stats(env, [actor, critic])
    # A curriculum shows one sample for a whole run: ψ keeps the samples' scale all the same.
    one_sample = obs["actor"].clone()
    one_sample[:, columns] = float(data.psi[0])
    actor.update(one_sample)
    critic.update(torch.cat([one_sample, obs["critic"][:, env.actor_obs_dim:]], dim=-1))
    for norm in (actor, critic):
        assert norm.mean[columns].tolist() == pytest.approx([mean] * 5)
        assert norm.var[columns].tolist() == pytest.approx([var] * 5)
    with pytest.raises(PipelineInputError, match="psi_scale"):
        quiet_cfg(observations={"psi_scale": "fixed"}).validate()
