"""Trains the balance policy with the pipeline's PPO (`pipeline.rl.trainer.Trainer`) on `BalanceEnv`.

The actor is a stage-1 actor without the phase output; the double critic's sparse group sees the
falls (undiscounted), the dense group the standing terms. Chunked and resumable like every training
(`chunk_s`, `resume`), so a long run spreads over several sittings.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pipeline.balance.config import BalanceConfig
from pipeline.balance.starts import load_start_states
from pipeline.envs.balance_env import BalanceEnv
from pipeline.rl.networks import DoubleCritic, Stage1Policy
from pipeline.rl.trainer import Trainer
from pipeline.rl.training import policy_meta, seed_everything

TASK = "balance"


def make_balance_env(cfg: BalanceConfig, root: Path, num_envs: int | None = None, env_cfg=None) -> BalanceEnv:
    states = load_start_states(cfg.start_states_path(root))
    return BalanceEnv(env_cfg or cfg.env, num_envs=num_envs or cfg.train.ppo.num_envs, start_states=states,
                      backend=cfg.train.backend, device=cfg.train.device)


def nominal_phase_rate(env: BalanceEnv) -> float:
    """The actor's phase head is off (no phase); its unused bound is sized as if an episode were a phase."""
    return 1.0 / env.max_steps


def balance_meta(env: BalanceEnv, cfg: BalanceConfig) -> dict:
    @dataclasses.dataclass
    class _Task:
        task: str = TASK

    meta = policy_meta(env, _Task(), cfg.train, 1, nominal_phase_rate(env))
    meta["outputs"] = ["joint_action (scaled offset from the default joint positions)"]
    meta["env_config"] = cfg.env.to_dict()
    return meta


def train_balance(cfg: BalanceConfig, run_dir: str | Path, *, root: Path = Path("."), resume: bool = False,
                  chunk_s: float | None = None, env: BalanceEnv | None = None, **trainer_kwargs) -> dict:
    """PPO on the balance env; the policy goes to run_dir/policy (config.json + model.safetensors)."""
    train = cfg.train
    seed_everything(train.seed)
    env = env if env is not None else make_balance_env(cfg, root)
    net, spec = train.network, env.spec()
    policy = Stage1Policy(spec.actor_obs_dim, spec.action_dim, net.actor_hidden, net.activation, net.init_log_std,
                          adaptive_phase=False, phase_rate=nominal_phase_rate(env), normalize_obs=train.ppo.normalize_obs)
    critic = DoubleCritic(spec.critic_obs_dim, net.critic_hidden, net.activation, train.ppo.normalize_obs)
    trainer = Trainer(env, policy, critic, train, run_dir, stage=1, meta=balance_meta(env, cfg), l2c2=False,
                      **trainer_kwargs)
    if cfg.init_from and (not resume or trainer.checkpoints.latest() is None):
        trainer.warm_start(root / cfg.init_from)
    return trainer.run(cfg.iterations, resume=resume, time_limit_s=cfg.time_limit_s or None, chunk_s=chunk_s)
