"""Double-critic PPO, stage-2 adapters, normalisers, L2C2, AMP and the training config, on the small keyframe-reaching
toy env (tests/toy_keyframe_env.py)."""

from __future__ import annotations

import json

import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.rl.amp import AMPDiscriminator, reference_windows
from pipeline.rl.checkpoint import load_policy
from pipeline.rl.config import VARIANTS, TrainConfig
from pipeline.rl.networks import DoubleCritic, EmpiricalNormalizer, Stage1Policy
from pipeline.rl.ppo import gae
from pipeline.rl.stage2 import Stage2Policy
from pipeline.rl.trainer import Trainer

from toy_keyframe_env import META, ToyKeyframeEnv, evaluate, make_stage1, small_cfg

torch.set_num_threads(1)


# ------------------------------------------------------------------------------------------ GAE
def test_gae_per_group_matches_hand_computation():
    rewards = torch.tensor([[1.0, -1.0], [2.0, 0.0], [3.0, 1.0]])
    values = torch.tensor([[0.5, 0.0], [0.6, 0.0], [0.7, 0.0]])
    last = torch.tensor([0.8, 1.0])
    terminated = torch.tensor([[False, True], [False, False], [False, False]])
    # env 0 times out at t=1 (bootstrap value 0.9); env 1 terminates and times out at t=0 (no bootstrap).
    truncated = torch.tensor([[False, True], [True, False], [False, False]])
    timeout_values = torch.tensor([[0.0, 5.0], [0.9, 0.0], [0.0, 0.0]])

    dense_adv, dense_ret = gae(rewards, values, last, terminated, truncated, 0.9, 0.8, timeout_values)
    a2 = 3.0 + 0.9 * 0.8 - 0.7
    a1 = 2.0 + 0.9 * 0.9 - 0.6  # bootstrapped at the timeout, trace cut
    a0 = (1.0 + 0.9 * 0.6 - 0.5) + 0.9 * 0.8 * a1
    b2 = 1.0 + 0.9 * 1.0
    b1 = 0.0 + 0.9 * 0.8 * b2
    b0 = -1.0  # terminated: neither the next value nor the timeout value
    expected = torch.tensor([[a0, b0], [a1, b1], [a2, b2]])
    assert torch.allclose(dense_adv, expected, atol=1e-6)
    assert torch.allclose(dense_ret, expected + values, atol=1e-6)

    sparse_adv, _ = gae(rewards, values, last, terminated, truncated, 1.0, 0.8, None)
    s2 = 3.0 + 0.8 - 0.7
    s1 = 2.0 - 0.6  # timeout ends the return: no bootstrap in the sparse group
    s0 = (1.0 + 0.6 - 0.5) + 0.8 * s1
    t2 = 1.0 + 1.0
    t1 = 0.8 * t2
    assert torch.allclose(sparse_adv, torch.tensor([[s0, -1.0], [s1, t1], [s2, t2]]), atol=1e-6)


# ------------------------------------------------------------------------------------------ learning
def test_ppo_improves_return_on_toy_keyframe_task(tmp_path):
    cfg = small_cfg()
    torch.manual_seed(0)
    env = ToyKeyframeEnv(cfg.ppo.num_envs)
    policy, critic = make_stage1(env, cfg)
    before = evaluate(policy)
    trainer = Trainer(env, policy, critic, cfg, tmp_path, stage=1, meta=META, l2c2=True, tensorboard=False, progress=False)
    metrics = trainer.run(40)
    after = evaluate(policy)
    # The optimum is ~20 sparse + ~5 dense; doing nothing scores ~3.
    assert after > before + 8.0, (before, after)
    assert after > 15.0, after
    assert env.curriculum_calls and env.curriculum_calls[-1] == pytest.approx(39 / 40)
    assert metrics["success_rate"] is not None and metrics["success_rate"] > 0.8
    assert (tmp_path / "training_curve.png").stat().st_size > 0
    assert json.loads((tmp_path / "metrics.json").read_text())["iterations"] == 40
    loaded, meta = load_policy(tmp_path / "policy", {"robot": "toy", "obs_layout": {"pos": 2, "phase": 1}})
    obs = torch.randn(5, 3)
    assert torch.equal(loaded(obs)[0], policy.eval()(obs)[0])


# ------------------------------------------------------------------------------------------ stage 2
def _stage2(freeze=True, seed=0):
    cfg = small_cfg()
    env = ToyKeyframeEnv(cfg.ppo.num_envs)
    base, _ = make_stage1(env, cfg, seed)
    base.normalizer.update(torch.randn(100, 3) * 2 + 1)
    torch.manual_seed(seed + 1)
    return Stage2Policy(base, [16], freeze_base=freeze, phase_rate=env.dphi), env, cfg


def test_stage2_action_equals_stage1_at_zero_phase_offset():
    policy, _, _ = _stage2()
    with torch.no_grad():
        for p in policy.track_adapter.parameters():  # a large, non-trivial a^Δ
            p.add_(torch.randn_like(p))
    obs = torch.randn(32, 3)
    a_delta = 10 * torch.randn(32, 2)
    base_action = policy.base(obs)[0]
    assert torch.equal(policy.compose(obs, torch.zeros(32), a_delta), base_action)
    raw = torch.cat([torch.zeros(32, 1), a_delta], -1)  # u_phase = 0 maps to Δφ^Δ = 0
    action, dphi = policy.to_env(obs, raw)
    assert dphi.abs().max() < 1e-9
    assert torch.allclose(action, base_action, atol=1e-6)
    # and Δφ^Δ != 0 really changes the action; bounds hold at the extremes
    moved, _ = policy.to_env(obs, torch.cat([torch.ones(32, 1), a_delta], -1))
    assert (moved - base_action).abs().max() > 0.1
    extremes = policy.phase_bound(torch.tensor([-50.0, 50.0]))
    assert torch.allclose(extremes, torch.tensor([-0.75 * policy.phase_rate, policy.phase_rate]), atol=1e-7)


@pytest.mark.parametrize("freeze", [True, False])
def test_stage2_update_keeps_frozen_stage1_parameters(tmp_path, freeze):
    policy, env, cfg = _stage2(freeze)
    base_before = {k: v.clone() for k, v in policy.base.state_dict().items()}
    adapter_before = [p.clone() for p in policy.track_adapter.parameters()]
    critic = DoubleCritic(env.critic_obs_dim, [32], "elu")
    meta = dict(META, stage=2)
    Trainer(env, policy, critic, cfg, tmp_path, stage=2, meta=meta, use_phase_offset=True,
            tensorboard=False, progress=False).run(2)
    base_after = policy.base.state_dict()
    unchanged = all(torch.equal(base_before[k], base_after[k]) for k in base_before)
    assert unchanged == freeze
    assert any(not torch.equal(a, b) for a, b in zip(adapter_before, policy.track_adapter.parameters()))
    loaded, meta = load_policy(tmp_path / "policy")
    obs = torch.randn(4, 3)
    assert isinstance(loaded, Stage2Policy)
    for got, want in zip(loaded(obs), policy.eval()(obs)):
        assert torch.equal(got, want)


# ------------------------------------------------------------------------------------------ AMP
def test_amp_style_reward_in_sparse_group(tmp_path):
    # Seeded: unseeded, it read the RNG state the tests before it left, and after 2 iterations the
    # discriminator separated the two sides at 7 seeds of 10; after 4, at 10 of 10.
    torch.manual_seed(0)
    cfg = small_cfg(variant="amp_style")
    ref = torch.cumsum(torch.full((40, 2), 0.05), 0).numpy()
    windows = reference_windows(ref, 5, with_phase=False)
    assert windows.shape == (36, 10)
    amp = AMPDiscriminator(10, cfg.amp)
    env = ToyKeyframeEnv(cfg.ppo.num_envs)
    policy, critic = make_stage1(env, cfg)
    trainer = Trainer(env, policy, critic, cfg, tmp_path, stage=1, meta=META, amp=amp, amp_reference=windows,
                      tensorboard=False, progress=False)
    trainer.run(4)
    h = trainer.history[-1]
    assert h["disc_real"] > h["disc_fake"]  # the discriminator separates reference from policy
    style = amp.style_reward(windows)
    assert ((style >= 0) & (style <= 1)).all()
    combined = amp.combine({"sparse": torch.ones(3), "dense": torch.ones(3)}, torch.ones(3))
    assert torch.allclose(combined["sparse"], torch.full((3,), 1.0)) and torch.allclose(combined["dense"], torch.full((3,), 0.9))


# ------------------------------------------------------------------------------------------ config / bad input
def test_config_profiles_and_variants():
    gpu = TrainConfig.from_dict({"profile": "gpu"})
    assert (gpu.ppo.num_envs, gpu.ppo.steps_per_iteration, gpu.ppo.epochs) == (4096, 75, 5)
    assert gpu.network.actor_hidden == [512, 256, 128] and gpu.ppo.kl_target == 0.01 and gpu.ppo.learning_rate == 1e-3
    assert (gpu.ppo.gamma_sparse, gpu.ppo.gamma_dense, gpu.ppo.adv_weight_dense) == (1.0, 0.99, 0.5)
    cpu = TrainConfig.from_dict({})
    assert cpu.profile == "cpu" and cpu.variant == "adamimic" and cpu.ppo.num_envs <= 256
    assert TrainConfig.from_dict({"variant": "adamimic_nofreeze"}).variant_spec.freeze_stage1 is False
    assert len(VARIANTS) == 10 and not VARIANTS["deepmimic_noadapt"].keyframe_rewards
    assert VARIANTS["deepmimic_noadapt"].reference == "original" and VARIANTS["amp_mimic"].amp == "mimic"


@pytest.mark.parametrize("raw, field", [
    ({"variant": "adamimc"}, "variant"),
    ({"profile": "tpu"}, "profile"),
    ({"ppo": {"num_env": 3}}, "num_env"),
    ({"ppo": {"num_envs": 0}}, "ppo.num_envs"),
    ({"ppo": {"epochs": "five"}}, "epochs"),
    ({"network": {"activation": "gelu"}}, "network.activation"),
])
def test_bad_train_config_names_the_key(raw, field):
    with pytest.raises(PipelineInputError) as err:
        TrainConfig.from_dict(raw)
    assert field in str(err.value)


# ------------------------------------------------------------------------------------------ critic scale, clipping
def test_return_normaliser_scales_the_regression_and_round_trips():
    torch.manual_seed(0)
    critic = DoubleCritic(4, [8])
    obs = torch.randn(6, 4)
    raw_sparse, raw_dense = critic.normalized(obs)
    assert torch.equal(critic(obs)[0], raw_sparse)  # untouched statistics: identity
    returns = 800.0 + 300.0 * torch.randn(5000)  # sparse returns of the far jump's order
    for _ in range(300):
        critic.sparse_returns.update(returns)
    assert critic.sparse_returns.normalize(returns).mean().abs() < 0.01
    assert critic.sparse_returns.normalize(returns).std() == pytest.approx(1.0, abs=0.02)
    x = torch.randn(10)
    assert torch.allclose(critic.sparse_returns.normalize(critic.sparse_returns.denormalize(x)), x, atol=1e-5)
    assert torch.allclose(critic(obs)[0], critic.sparse_returns.denormalize(raw_sparse))
    assert critic(obs)[0].abs().min() > 100.0  # values in reward units for GAE
    assert torch.equal(critic(obs)[1], raw_dense)  # the other group keeps its own (untouched) statistics


def test_actor_gradient_is_not_scaled_by_the_critics(tmp_path):
    """Actor and critics are clipped apart: a huge value loss must not shrink the policy's step."""
    from pipeline.rl.ppo import PPO, Rollout

    cfg = small_cfg()
    torch.manual_seed(0)
    env = ToyKeyframeEnv(cfg.ppo.num_envs)
    policy, critic = make_stage1(env, cfg)
    ppo = PPO(policy, critic, cfg.ppo)
    ro = Rollout.allocate(4, env.num_envs, env.actor_obs_dim, env.critic_obs_dim, policy.raw_dim, "cpu")
    ro.actor_obs.normal_()
    ro.critic_obs.normal_()
    rec = ppo.act(ro.actor_obs.reshape(-1, 3), ro.critic_obs.reshape(-1, 4))
    ro.raw_actions.copy_(rec["raw"].reshape(ro.raw_actions.shape))
    ro.log_probs.copy_(rec["log_prob"].reshape(ro.log_probs.shape))
    ro.means.copy_(rec["mean"].reshape(ro.means.shape))
    ro.stds.copy_(rec["std"].reshape(ro.stds.shape))
    ro.rewards["sparse"].normal_().mul_(1e4)  # returns far beyond the critic's reach
    ro.rewards["dense"].normal_()
    stats = ppo.update(ro)
    assert stats["grad_norm_actor"] > 1e-3 and stats["grad_norm_critic"] > 1e-3
    assert stats["value_loss_sparse"] < 100.0  # regressed in units of the group's return spread


def test_episode_stats_record_each_finished_episode():
    """Three worlds over three steps: one falls, one times out, one times out after missing a keyframe
    by more than 1 m (a failure without a termination). The figures reach the window once, in order."""
    from pipeline.rl.episode_stats import EpisodeStats

    stats = EpisodeStats(3, "cpu", window=3)
    no = torch.zeros(3, dtype=torch.bool)
    steps = [  # (sparse, dense, terminated, truncated, crossed, body error (m), fell by tilt)
        ([1.0, 2.0, 3.0], [0.5, 0.5, 0.5], no, no, [False, False, True], [0.0, 0.0, 1.5], no),
        ([-200.0, 1.0, 1.0], [0.5, 0.5, 0.5], torch.tensor([True, False, False]), no, no.tolist(), [0.0] * 3,
         torch.tensor([True, False, False])),
        ([7.0, 1.0, 1.0], [0.25, 0.25, 0.25], no, torch.tensor([False, True, True]), no.tolist(), [0.0] * 3, no),
    ]
    for sparse, dense, terminated, truncated, crossed, err, tilt in steps:
        info = {"keyframe_crossed": torch.tensor(crossed), "body_pos_error_w": torch.tensor(err)[:, None].expand(3, 17),
                "terminated_by": {"tilt": tilt, "keyframe_error": no}}
        stats.step({"sparse": torch.tensor(sparse), "dense": torch.tensor(dense)}, terminated, truncated, info)
    ended = {"ended_by_tilt": 0.0, "ended_by_keyframe_error": 0.0}
    assert stats.finished == [
        {"success": 0.0, "length": 2.0, "sparse": -199.0, "dense": 1.0, **ended, "ended_by_tilt": 1.0},
        {"success": 1.0, "length": 3.0, "sparse": 4.0, "dense": 1.25, **ended},
        {"success": 0.0, "length": 3.0, "sparse": 5.0, "dense": 1.25, **ended},
    ]
    summary = stats.summary()
    assert summary["success_rate"] == pytest.approx(1 / 3) and summary["ended_by_tilt"] == pytest.approx(1 / 3)
    # world 0 restarted after its fall: one step of its next episode is counted from zero
    assert stats.steps.tolist() == [1, 0, 0] and stats.returns["sparse"].tolist() == [7.0, 0.0, 0.0]
    stats.step({"sparse": torch.ones(3), "dense": torch.ones(3)}, torch.tensor([True, False, False]), no,
               {"terminated_by": {"tilt": no, "keyframe_error": no}})
    restored = EpisodeStats(3, "cpu", window=3)
    restored.load_state_dict(stats.state_dict())
    assert restored.finished == stats.finished and len(stats.finished) == 3  # the window keeps the last 3
    assert stats.finished[-1] == {"success": 0.0, "length": 2.0, "sparse": 8.0, "dense": 1.25,
                                  "ended_by_tilt": 0.0, "ended_by_keyframe_error": 0.0}


def test_l2c2_on_a_share_of_the_minibatch():
    """ppo.l2c2_fraction: the L2C2 terms see that share of the minibatch (its head, a random subset
    since minibatches are slices of a permutation), less the samples with no next observation."""
    from pipeline.rl.ppo import PPO

    seen = []
    for fraction in (1.0, 0.25):
        cfg = TrainConfig.from_dict({"ppo": {"l2c2_fraction": fraction}})
        policy, critic = Stage1Policy(3, 2, [8]), DoubleCritic(4, [8])
        ppo = PPO(policy, critic, cfg.ppo, l2c2=True)
        raw_mean = policy.raw_mean
        policy.raw_mean = lambda obs: (seen.append((fraction, obs.shape[0])), raw_mean(obs))[1]
        total, num_envs = 200, 10
        idx = torch.randperm(total - num_envs)[:100]  # every sample here has a next one ...
        has_next = torch.ones(total, dtype=torch.bool)
        has_next[idx[:4]] = False  # ... but four
        mean = torch.zeros(100, 2)
        values = {"sparse": torch.zeros(100), "dense": torch.zeros(100)}
        loss = ppo._l2c2(idx, torch.randn(total, 3), torch.randn(total, 4), has_next, num_envs, mean, values)
        assert loss > 0
    assert seen == [(1.0, 96), (0.25, 21)]
    with pytest.raises(PipelineInputError, match="l2c2_fraction"):
        TrainConfig.from_dict({"ppo": {"l2c2_fraction": 0.0}})


def test_pinned_normalizer_columns_hold_through_updates_and_a_reload():
    norm = EmpiricalNormalizer(4)
    norm.pin([1, 3], mean=1.1, var=0.25)
    for _ in range(5):
        norm.update(3.0 * torch.randn(200, 4) + 5.0)
    assert norm.mean[[1, 3]].tolist() == pytest.approx([1.1, 1.1]) and norm.var[[1, 3]].tolist() == pytest.approx([0.25, 0.25])
    assert norm.mean[[0, 2]].tolist() == pytest.approx([5.0, 5.0], abs=0.5)  # the rest still track the data
    assert norm.var[[0, 2]].tolist() == pytest.approx([9.0, 9.0], rel=0.2)
    # The mask is not saved, so checkpoints keep their keys; the pinned values travel in mean/var.
    assert set(norm.state_dict()) == {"mean", "var", "count"}
    reloaded = EmpiricalNormalizer(4)
    reloaded.load_state_dict(norm.state_dict())
    x = torch.randn(8, 4)
    assert torch.equal(reloaded(x), norm(x))
    # Pinning without values holds what the columns have now.
    reloaded.pin([0])
    before = float(reloaded.mean[0])
    reloaded.update(torch.full((10, 4), -50.0))
    assert float(reloaded.mean[0]) == before and float(reloaded.mean[2]) < before
