"""TrackingEnv.state_dict/load_state_dict: a fresh env loaded from a snapshot continues bit for bit
(domain randomisation, pushes, control delay, RSI and odometry noise on), alone and under the trainer."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import EnvConfig
from pipeline.envs.tracking_env import TrackingEnv
from env_stand_clip import data  # noqa: F401  (the module fixture: a 61-frame standing clip, 3 keyframes)

N = 6


def noisy_cfg(sampling: str = "adaptive") -> EnvConfig:
    # everything random on; pushes often so a few steps see some; ψ drawn by a sampler with its own state
    # (failure rates, or per-world curriculum levels)
    return EnvConfig.from_dict({"rsi_prob": 0.5, "randomization": {"push": {"interval_s": [0.04, 0.2]}},
                                "sampling": {"mode": sampling, "levels": 3}})


def run(env, actions):
    out = []
    for a in actions:
        obs, rew, term, trunc, info = env.step(a)
        out.append((obs["actor"], obs["critic"], rew["sparse"], rew["dense"], term, trunc,
                    info["final_obs"]["critic"], info["sample"]))
    return out


def resumed_env(cfg, data, env, actions):  # noqa: F811
    """Snapshots `env`, steps it through `actions`, and does the same from the snapshot in a fresh env built
    under another seed: every output must be equal. Returns the fresh env."""
    state, rng = env.state_dict(), torch.get_rng_state()
    expected = run(env, actions)
    torch.manual_seed(5)
    fresh = TrackingEnv(cfg, data, num_envs=N)
    fresh.reset()
    fresh.load_state_dict(state)
    torch.set_rng_state(rng)
    got = run(fresh, actions)
    for t, (e, g) in enumerate(zip(expected, got)):
        for i, (a, b) in enumerate(zip(e, g)):
            assert torch.equal(a, b), f"step {t}, output {i}"
    assert any(bool((e[4] | e[5]).any()) for e in expected), "no episode ended: no restart was drawn"
    return fresh


@pytest.mark.parametrize("sampling", ["adaptive", "curriculum"])
def test_fresh_env_continues_bit_for_bit_after_load(data, sampling):  # noqa: F811
    cfg = noisy_cfg(sampling)
    assert cfg.randomization.enabled
    torch.manual_seed(0)
    env = TrackingEnv(cfg, data, num_envs=N)
    env.reset()
    env.update_curriculum(0.3)
    for _ in range(12):
        env.step(torch.randn(N, env.action_dim) * 0.5)
    actions = [torch.randn(N, env.action_dim) * 0.5 for _ in range(25)]  # drawn before the RNG snapshot
    state = env.state_dict()
    rng = torch.get_rng_state()
    # the snapshot holds only CPU data (and copies: stepping on must not change it)
    assert state["qpos"].dtype == torch.float64
    assert all(v.device.type == "cpu" for v in state["buffers"].values())
    phase_at_save = state["buffers"]["phase"].clone()
    expected = run(env, actions)
    assert torch.equal(state["buffers"]["phase"], phase_at_save)
    assert any(bool((e[4] | e[5]).any()) for e in expected), "no episode ended: resets are not exercised"

    torch.manual_seed(123)  # a fresh env with other randomisation: everything must come from the snapshot
    fresh = TrackingEnv(cfg, data, num_envs=N)
    fresh.reset()
    fresh.load_state_dict(state)
    torch.set_rng_state(rng)  # the caller's RNG (the trainer restores its own)
    got = run(fresh, actions)
    for t, (e, g) in enumerate(zip(expected, got)):
        for i, (a, b) in enumerate(zip(e, g)):
            assert torch.equal(a, b), f"step {t}, output {i}"
    assert fresh.termination_threshold == env.termination_threshold and fresh.penalty_scale == env.penalty_scale
    assert torch.equal(fresh.sampler.level, env.sampler.level)
    assert torch.equal(fresh.sampler.failure_rate, env.sampler.failure_rate)
    ids = np.arange(N)
    for name in ("body_mass", "geom_friction", "actuator_gainprm"):
        assert np.array_equal(fresh.backend.get_model_field(name, ids), env.backend.get_model_field(name, ids))


def test_own_state_ring_is_part_of_the_snapshot(data):  # noqa: F811
    """With restarts from the policy's own states on, the ring of recorded states resumes too."""
    raw = {"rsi_prob": 0.5, "randomization": {"push": {"interval_s": [0.04, 0.2]}},
           "own_state_starts": {"prob": 0.5, "at_label": "apex", "capacity": 4}}
    cfg = EnvConfig.from_dict(raw)
    torch.manual_seed(0)
    env = TrackingEnv(cfg, data, num_envs=N)
    env.reset()
    for _ in range(40):  # past the apex (frame 25): the ring holds states
        env.step(torch.randn(N, env.action_dim) * 0.3)
    assert len(env.own_states) > 0
    actions = [torch.randn(N, env.action_dim) * 0.3 for _ in range(40)]
    fresh = resumed_env(cfg, data, env, actions)
    assert torch.equal(fresh.own_states.entries["qpos"], env.own_states.entries["qpos"])


def test_load_rejects_another_number_of_worlds(data):  # noqa: F811
    state = TrackingEnv(noisy_cfg(), data, num_envs=2).state_dict()
    with pytest.raises(PipelineInputError, match="num_envs"):
        TrackingEnv(noisy_cfg(), data, num_envs=3).load_state_dict(state)


@pytest.mark.parametrize("noise_correlation", [0.0, 0.9])
def test_trainer_resume_on_the_tracking_env_is_bit_for_bit(tmp_path, data, noise_correlation):  # noqa: F811
    from pipeline.rl.trainer import Trainer
    from toy_keyframe_env import META, make_stage1, small_cfg

    cfg = small_cfg(save_interval=1, ppo={"num_envs": 8, "steps_per_iteration": 8, "epochs": 1, "minibatches": 2,
                                          "noise_correlation": noise_correlation})

    def trainer(run_dir, seed):
        torch.manual_seed(seed)
        env = TrackingEnv(noisy_cfg(), data, num_envs=cfg.ppo.num_envs)
        policy, critic = make_stage1(env, cfg, seed)
        meta = {**META, "robot": "g1", "action_dim": env.action_dim, "actor_obs_dim": env.actor_obs_dim,
                "critic_obs_dim": env.critic_obs_dim, "obs_layout": env.obs_layout(), "phase_rate": env.dphi}
        return Trainer(env, policy, critic, cfg, run_dir, stage=1, meta=meta, tensorboard=False, progress=False)

    straight = trainer(tmp_path / "a", 0)
    straight.run(2)
    trainer(tmp_path / "b", 0).run(1)  # "killed" after the checkpoint at iteration 1
    # the checkpoint carries the env (so the trainer does not restart episodes at its boundaries)
    from pipeline.rl.checkpoint import CheckpointManager
    ckpt = CheckpointManager(tmp_path / "b").latest()
    assert "env" in CheckpointManager.load_state(ckpt)
    resumed = trainer(tmp_path / "b", 99)  # other init and other env randomisation: all must come from disk
    resumed.run(2, resume=True)
    for (k, a), b in zip(straight.policy.state_dict().items(), resumed.policy.state_dict().values()):
        assert torch.equal(a, b), k
    for a, b in zip(straight.critic.state_dict().values(), resumed.critic.state_dict().values()):
        assert torch.equal(a, b)
    assert straight.history[-1]["policy_loss"] == resumed.history[-1]["policy_loss"]
    assert straight.history[-1]["reward_dense"] == resumed.history[-1]["reward_dense"]
    assert straight.env.penalty_scale == resumed.env.penalty_scale


def test_adaptive_start_frames_are_part_of_the_snapshot(data):  # noqa: F811
    """With adaptive reference-state start frames, the per-group failure rates resume too."""
    raw = {"rsi_prob": 1.0, "randomization": {"push": {"interval_s": [0.04, 0.2]}},
           "rsi_sampling": {"mode": "adaptive", "bins": 4, "rate_smoothing": 0.5}}
    cfg = EnvConfig.from_dict(raw)
    torch.manual_seed(0)
    env = TrackingEnv(cfg, data, num_envs=N)
    env.reset()
    for _ in range(60):  # random actions fall: episodes end and are charged to their start groups
        env.step(torch.randn(N, env.action_dim))
    assert (env.start_sampler.failure_rate < 1.0).any(), "no group saw an episode end"
    actions = [torch.randn(N, env.action_dim) for _ in range(40)]
    fresh = resumed_env(cfg, data, env, actions)
    assert torch.equal(fresh.start_sampler.failure_rate, env.start_sampler.failure_rate)
