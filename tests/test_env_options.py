"""TrackingEnv's options: domain randomisation, control delay, action offsets, bad input, terrain per ψ,
the dense variant, the compiled step, pushes, feed-forward torques and the ψ input's scale."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import EnvConfig
from pipeline.envs.tracking_env import FRAME_OBS_DIM, TrackingEnv
from pipeline.keyframes.tracking_data import TrackingData

from env_stand_clip import KEYFRAMES, N, data, hold, quiet_cfg  # noqa: F401  (data: the module fixture)


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
