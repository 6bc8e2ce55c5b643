"""Double-critic PPO, stage-2 adapters, checkpoints and config, on a small keyframe-reaching toy env.

The toy env follows the TrackingEnv contract: a 2-D point mass must be near keyframe targets at two
fixed steps (sparse group, like AdaMimic's keyframe rewards) while following a reference path and
not using large actions (dense group); leaving the arena terminates with a penalty; the episode
times out after `horizon` steps. It draws all randomness from torch's global RNG.
"""

from __future__ import annotations

import json

import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.rl.amp import AMPDiscriminator, reference_windows
from pipeline.rl.averaging import WeightAverage
from pipeline.rl.checkpoint import load_policy, save_policy
from pipeline.rl.config import VARIANTS, TrainConfig
from pipeline.rl.networks import DoubleCritic, EmpiricalNormalizer, Stage1Policy
from pipeline.rl.ppo import gae
from pipeline.rl.stage2 import Stage2Policy
from pipeline.rl.trainer import Trainer
from pipeline.rl.training import train_stage2

torch.set_num_threads(1)


class ToyKeyframeEnv:
    horizon = 16
    keyframes = {7: torch.tensor([1.0, 0.0]), 15: torch.tensor([1.0, 1.0])}

    def __init__(self, num_envs: int = 64):
        self.num_envs, self.action_dim = num_envs, 2
        self.actor_obs_dim, self.critic_obs_dim = 3, 4
        self.dphi = 1.0 / self.horizon
        self.obs_layout = {"pos": 2, "phase": 1}
        self.joint_names = ["x", "y"]
        self.pos = torch.zeros(num_envs, 2)
        self.t = torch.zeros(num_envs, dtype=torch.long)
        self.curriculum_calls = []

    # the trainer's contract (pipeline/envs/spec.py); no state to save: restarted at checkpoint boundaries
    def spec(self):
        from pipeline.envs.spec import EnvSpec

        return EnvSpec(num_envs=self.num_envs, action_dim=self.action_dim, actor_obs_dim=self.actor_obs_dim,
                       critic_obs_dim=self.critic_obs_dim, joint_names=tuple(self.joint_names),
                       obs_layout=self.obs_layout, phase_rate=self.dphi, resumable=False)

    def update_curriculum(self, progress):
        self.curriculum_calls.append(progress)

    def curriculum_stats(self):
        return {}

    def pinned_observation_stats(self):
        return []

    def _reference(self, t):
        # straight line to the first keyframe, then up to the second
        s = (t.float() + 1) / 8.0
        first = torch.stack([s.clamp(max=1.0), torch.zeros_like(s)], -1)
        return first + torch.stack([torch.zeros_like(s), (s - 1.0).clamp(0.0, 1.0)], -1)

    def _obs(self):
        phase = (self.t.float() / self.horizon).unsqueeze(-1)
        actor = torch.cat([self.pos, phase], -1)
        return {"actor": actor, "critic": torch.cat([actor, phase**2], -1)}

    def _reset(self, ids):
        self.pos[ids] = 0.05 * torch.randn(len(ids), 2)
        self.t[ids] = 0

    def reset(self):
        self._reset(torch.arange(self.num_envs))
        return self._obs()

    def step(self, action, phase_rate_offset=None):
        action = action.clamp(-1.0, 1.0)
        self.pos = self.pos + 0.25 * action
        sparse = torch.zeros(self.num_envs)
        crossed = torch.zeros(self.num_envs, dtype=torch.bool)
        err = torch.zeros(self.num_envs, 1)
        for step, target in self.keyframes.items():
            hit = self.t == step
            dist = (self.pos - target).norm(dim=-1)
            sparse += hit * 10.0 * torch.exp(-(dist**2) / 0.1)
            crossed |= hit
            err[hit, 0] = dist[hit]
        ref_err = (self.pos - self._reference(self.t)).norm(dim=-1)
        dense = 0.5 * torch.exp(-(ref_err**2) / 0.25) - 0.05 * (action**2).sum(-1)
        terminated = self.pos.norm(dim=-1) > 2.5
        sparse -= 10.0 * terminated
        self.t += 1
        truncated = (self.t >= self.horizon) & ~terminated
        final = self._obs()
        info = {"keyframe_crossed": crossed, "body_pos_error_w": err, "final_obs": final,
                "phase": self.t.float() / self.horizon, "joint_pos": self.pos.clone()}
        done = (terminated | truncated).nonzero().flatten()
        if len(done):
            self._reset(done)
        return self._obs(), {"sparse": sparse, "dense": dense}, terminated, truncated, info


def small_cfg(**over) -> TrainConfig:
    raw = {"ppo": {"num_envs": 64, "steps_per_iteration": 16, "epochs": 4, "minibatches": 4, "learning_rate": 3e-3},
           "network": {"actor_hidden": [32, 32], "critic_hidden": [32, 32], "adapter_hidden": [16], "init_log_std": -0.5},
           "save_interval": 5}
    raw.update(over)
    return TrainConfig.from_dict(raw)


def make_stage1(env, cfg, seed=0):
    torch.manual_seed(seed)
    net = cfg.network
    policy = Stage1Policy(env.actor_obs_dim, env.action_dim, net.actor_hidden, net.activation, net.init_log_std,
                          phase_rate=env.dphi)
    critic = DoubleCritic(env.critic_obs_dim, net.critic_hidden, net.activation)
    return policy, critic


META = {"robot": "toy", "joint_names": ["x", "y"], "action_dim": 2, "actor_obs_dim": 3, "critic_obs_dim": 4,
        "obs_layout": {"pos": 2, "phase": 1}, "phase_rate": 1.0 / 16, "stage": 1, "variant": "adamimic",
        "architecture": {"actor_hidden": [32, 32], "critic_hidden": [32, 32], "adapter_hidden": [16],
                         "activation": "elu", "adaptive_phase": False, "freeze_base": True, "normalize_obs": True}}


@torch.no_grad()
def evaluate(policy, episodes_envs: int = 256) -> float:
    """Mean undiscounted return (sparse + dense) of the deterministic policy over one episode."""
    torch.manual_seed(123)
    env = ToyKeyframeEnv(episodes_envs)
    obs = env.reset()
    total = torch.zeros(episodes_envs)
    alive = torch.ones(episodes_envs, dtype=torch.bool)
    for _ in range(env.horizon):
        action, _ = policy(obs["actor"])
        obs, rew, term, trunc, _ = env.step(action)
        total += alive * (rew["sparse"] + rew["dense"])
        alive &= ~(term | trunc)
    return total.mean().item()


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


# ------------------------------------------------------------------------------------------ resume
def _trainer(run_dir, cfg, seed):
    torch.manual_seed(seed)
    env = ToyKeyframeEnv(cfg.ppo.num_envs)
    policy, critic = make_stage1(env, cfg, seed)
    return Trainer(env, policy, critic, cfg, run_dir, stage=1, meta=META, l2c2=True, tensorboard=False, progress=False)


@pytest.mark.parametrize("noise_correlation", [0.0, 0.9])
def test_resume_reproduces_the_next_iteration_bit_for_bit(tmp_path, noise_correlation):
    cfg = small_cfg(save_interval=2, ppo={"num_envs": 32, "steps_per_iteration": 8, "epochs": 2, "minibatches": 2,
                                          "noise_correlation": noise_correlation})
    straight = _trainer(tmp_path / "a", cfg, seed=0)
    straight.run(3)
    interrupted = _trainer(tmp_path / "b", cfg, seed=0)
    interrupted.run(2)  # "killed" after the checkpoint at iteration 2
    resumed = _trainer(tmp_path / "b", cfg, seed=99)  # different init: everything must come from disk
    resumed.run(3, resume=True)
    for (k, a), b in zip(straight.policy.state_dict().items(), resumed.policy.state_dict().values()):
        assert torch.equal(a, b), k
    for a, b in zip(straight.critic.state_dict().values(), resumed.critic.state_dict().values()):
        assert torch.equal(a, b)
    assert straight.ppo.learning_rate == resumed.ppo.learning_rate
    assert [h["policy_loss"] for h in straight.history] == [h["policy_loss"] for h in resumed.history]


def test_a_warm_start_takes_the_networks_and_optimiser_but_counts_its_own_iterations(tmp_path):
    cfg = small_cfg(save_interval=2, ppo={"num_envs": 32, "steps_per_iteration": 8, "epochs": 2, "minibatches": 2})
    first = _trainer(tmp_path / "a", cfg, seed=0)
    first.run(2)
    tuned = _trainer(tmp_path / "b", cfg, seed=99)  # another init: what it starts from must come from the run
    assert not all(torch.equal(a, b) for a, b in zip(first.policy.state_dict().values(),
                                                      tuned.policy.state_dict().values()))
    tuned.warm_start(tmp_path / "a")
    for (k, a), b in zip(first.policy.state_dict().items(), tuned.policy.state_dict().values()):
        assert torch.equal(a, b), k
    for a, b in zip(first.critic.state_dict().values(), tuned.critic.state_dict().values()):
        assert torch.equal(a, b)
    assert tuned.ppo.learning_rate == first.ppo.learning_rate
    tuned.run(1)
    assert [h["iteration"] for h in tuned.history] == [1]
    with pytest.raises(PipelineInputError, match="training_state.pt"):
        tuned.warm_start(tmp_path / "nowhere")


def test_weight_average_means_floats_and_keeps_the_latest_of_the_rest():
    average = WeightAverage()
    average.add({"w": torch.tensor([1.0, 2.0]), "n": torch.tensor(3)})
    average.add({"w": torch.tensor([3.0, 6.0]), "n": torch.tensor(5)})
    mean = average.mean()
    assert torch.equal(mean["w"], torch.tensor([2.0, 4.0])) and mean["w"].dtype == torch.float32
    assert mean["n"].item() == 5
    with pytest.raises(ValueError, match="keys differ"):
        average.add({"w": torch.zeros(2)})


def test_average_tail_writes_the_mean_of_the_last_snapshots_and_survives_a_resume(tmp_path):
    from safetensors.torch import load_file

    cfg = small_cfg(save_interval=1, keep_checkpoints=4, average_tail=0.5, average_every=1,
                    ppo={"num_envs": 16, "steps_per_iteration": 4, "epochs": 1, "minibatches": 1})
    straight = _trainer(tmp_path / "a", cfg, seed=0)
    straight.run(4)
    # iterations 2, 3 and 4 end in the last half of the run; the live policy stays the last iteration's
    snapshots = [load_file(tmp_path / "a" / "checkpoints" / f"iter_{i:06d}" / "model.safetensors") for i in (2, 3, 4)]
    written = load_file(tmp_path / "a" / "policy" / "model.safetensors")
    for key, value in written.items():
        if key.startswith("policy.") and value.is_floating_point():
            want = (sum(s[key].double() for s in snapshots) / 3).to(value.dtype)
            assert torch.allclose(value, want, atol=1e-7), key
    assert not torch.equal(written["policy.body.0.weight"], snapshots[-1]["policy.body.0.weight"])
    assert json.loads((tmp_path / "a" / "policy" / "config.json").read_text())["averaged_snapshots"] == 3

    interrupted = _trainer(tmp_path / "b", cfg, seed=0)
    interrupted.run(3)  # killed after iteration 3's checkpoint, two snapshots into the average
    _trainer(tmp_path / "b", cfg, seed=99).run(4, resume=True)
    resumed = load_file(tmp_path / "b" / "policy" / "model.safetensors")
    for key, value in written.items():
        assert torch.equal(value, resumed[key]), key


@pytest.mark.parametrize("bad", [{"average_tail": -0.1}, {"average_tail": 1.5}, {"average_every": 0}])
def test_bad_average_settings_are_refused(bad):
    with pytest.raises(PipelineInputError, match=next(iter(bad))):
        small_cfg(**bad)


def test_curricula_follow_iterations_not_the_clock(tmp_path, monkeypatch):
    """A time limit only caps a run: on a slow (or busy) machine the same config trains the same policy,
    unless the cap stops it, which the run then reports. Sized by time alone (0 iterations), the curricula
    follow the clock."""
    import pipeline.rl.trainer as trainer_module

    cfg = small_cfg(ppo={"num_envs": 16, "steps_per_iteration": 4, "epochs": 1, "minibatches": 1})
    fast = _trainer(tmp_path / "fast", cfg, seed=0)
    fast.run(4)
    clock = iter(range(0, 10_000, 7))  # every reading 7 s later: 4 iterations take far more than 60 s of "wall time"
    monkeypatch.setattr(trainer_module.time, "time", lambda: float(next(clock)))
    slow = _trainer(tmp_path / "slow", cfg, seed=0)
    metrics = slow.run(4, time_limit_s=1000.0)
    assert slow.env.curriculum_calls == fast.env.curriculum_calls == [0.0, 0.25, 0.5, 0.75]
    for a, b in zip(fast.policy.state_dict().values(), slow.policy.state_dict().values()):
        assert torch.equal(a, b)
    assert metrics["stopped_by_time_limit"] is False

    messages = []
    capped = _trainer(tmp_path / "capped", cfg, seed=0)
    capped.log = messages.append
    metrics = capped.run(4, time_limit_s=20.0)
    assert metrics["iterations"] < 4 and metrics["stopped_by_time_limit"] is True
    assert any("time limit stopped it at iteration" in m for m in messages), messages
    assert json.loads((tmp_path / "capped" / "metrics.json").read_text())["stopped_by_time_limit"] is True

    by_time = _trainer(tmp_path / "by_time", cfg, seed=0)
    metrics = by_time.run(0, time_limit_s=60.0)
    calls = by_time.env.curriculum_calls
    assert metrics["iterations"] == len(calls) >= 2 and calls == sorted(calls) and 0 < calls[-1] <= 1.0
    with pytest.raises(ValueError, match="time limit"):
        _trainer(tmp_path / "none", cfg, seed=0).run(0)


def test_history_splits_each_iteration_into_collection_and_update(tmp_path):
    cfg = small_cfg(ppo={"num_envs": 16, "steps_per_iteration": 4, "epochs": 1, "minibatches": 1})
    trainer = _trainer(tmp_path, cfg, seed=0)
    trainer.run(3)
    for before, h in zip(trainer.history, trainer.history[1:]):
        assert h["collect_seconds"] > 0 and h["update_seconds"] > 0
        assert h["collect_seconds"] + h["update_seconds"] <= h["seconds"] - before["seconds"] + 1e-3


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


def test_checkpoint_from_another_robot_or_layout_is_refused(tmp_path):
    cfg = small_cfg()
    env = ToyKeyframeEnv(4)
    policy, critic = make_stage1(env, cfg)
    save_policy(tmp_path / "p", policy, critic, META)
    load_policy(tmp_path / "p", {"robot": "toy", "obs_layout": META["obs_layout"], "actor_obs_dim": 3})
    with pytest.raises(PipelineInputError, match="robot"):
        load_policy(tmp_path / "p", {"robot": "unitree_g1"})
    with pytest.raises(PipelineInputError, match="obs_layout"):
        load_policy(tmp_path / "p", {"robot": "toy", "obs_layout": {"pos": 2, "phase": 1, "psi": 1}})
    with pytest.raises(PipelineInputError, match="not a policy folder"):
        load_policy(tmp_path / "missing")
    # A policy saved before `action_offset` existed was trained around the default pose.
    load_policy(tmp_path / "p", {"robot": "toy", "action_offset": "default"})
    with pytest.raises(PipelineInputError, match="action_offset"):
        load_policy(tmp_path / "p", {"robot": "toy", "action_offset": "reference"})
    save_policy(tmp_path / "r", policy, critic, META | {"action_offset": "reference"})
    with pytest.raises(PipelineInputError, match="action_offset"):
        load_policy(tmp_path / "r", {"robot": "toy", "action_offset": "default"})


def test_stage2_without_stage1_checkpoint_is_refused(tmp_path):
    cfg = small_cfg()
    with pytest.raises(PipelineInputError, match="stage-1"):
        train_stage2(None, None, cfg, tmp_path / "s2", stage1_dir=tmp_path / "nothing", env=ToyKeyframeEnv(4))
    assert not (tmp_path / "s2").exists()


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
