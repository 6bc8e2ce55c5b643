"""The pipeline's training stages, on the loop in `pipeline/rl/trainer.py`:

    train_stage1(data, env_cfg, cfg, run_dir)                     -> metrics dict, policy in run_dir/policy
    train_stage2(data, env_cfg, cfg, run_dir, stage1_dir=...)     -> same, adapters on the frozen stage 1
    train(data, env_cfg, cfg, run_dir)                            -> both stages as the variant asks
"""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import start_episodes_at_zero
from pipeline.rl.amp import AMPDiscriminator, reference_windows
from pipeline.rl.checkpoint import load_policy
from pipeline.rl.config import TrainConfig, Variant
from pipeline.rl.networks import DoubleCritic, Stage1Policy
from pipeline.rl.stage2 import Stage2Policy
from pipeline.rl.trainer import Trainer


def phase_rate_of(env, data) -> float:
    """Δφ per control step: the env's (its spec), else one frame of the motion per step."""
    rate = env.spec().phase_rate
    if rate is not None:
        return float(rate)
    motion = data.motion
    return 1.0 / max(motion.num_frames - 1, 1)


def policy_meta(env, data, cfg: TrainConfig, stage: int, phase_rate: float, freeze_base: bool = True,
                output_bound: float = 0.0) -> dict:
    from pipeline.robot.g1 import load_robot_config

    robot, spec = load_robot_config(), env.spec()
    net, layout, action_offset = cfg.network, spec.obs_layout, spec.action_offset
    return {
        "robot": robot.name, "task": getattr(data, "task", None), "variant": cfg.variant, "stage": stage,
        # the trainer of this stage (stage 2 is always PPO)
        "algorithm": cfg.algorithm if stage == 1 else "ppo",
        "joint_names": list(spec.joint_names), "action_dim": int(spec.action_dim),
        "actor_obs_dim": int(spec.actor_obs_dim), "critic_obs_dim": int(spec.critic_obs_dim),
        "obs_layout": json.loads(json.dumps(layout, default=lambda x: list(x))) if layout is not None else None,
        "phase_rate": phase_rate,
        "action_offset": action_offset,
        # whether the zero action carries the task's push prior (priors/push_prior.py)
        "push_prior": bool(spec.push_prior),
        "architecture": {"actor_hidden": net.actor_hidden, "critic_hidden": net.critic_hidden,
                         "adapter_hidden": net.adapter_hidden, "activation": net.activation,
                         "adaptive_phase": bool(cfg.variant_spec.adaptive_phase_stage1),
                         "freeze_base": freeze_base, "normalize_obs": cfg.ppo.normalize_obs,
                         "output_bound": output_bound},
        "outputs": [f"joint_action (scaled offset from the {action_offset} joint positions)", "phase_rate_offset"],
        "train_config": cfg.to_dict(),
    }


def make_env(data, env_cfg, cfg: TrainConfig, *, stage: int, go_states: dict | None = None, handoff=None):
    """The training env of a stage; `go_states`: where the balance policy hands over (env.go_starts);
    `handoff`: where the chain hands back to it (envs/handoff_catch.py `Handoff`, for `handoff_catch`)."""
    from pipeline.envs.tracking_env import TrackingEnv

    env_cfg = env_config_for(env_cfg, cfg.variant_spec, stage)
    return TrackingEnv(env_cfg, data, num_envs=cfg.num_envs(stage), backend=cfg.backend, device=cfg.device, seed=cfg.seed,
                       go_states=go_states, handoff=handoff)


def env_config_for(env_cfg, variant: Variant, stage: int):
    """The env settings a variant and stage imply: keyframe (sparse) or every-step (dense) global
    tracking, the adaptive phase in stage 1 for *_dphi, and episodes from t = 0 in stage 2."""
    if not dataclasses.is_dataclass(env_cfg):
        return env_cfg
    env_cfg = copy.deepcopy(env_cfg)
    if hasattr(env_cfg, "variant"):
        env_cfg.variant.tracking = "sparse" if variant.keyframe_rewards else "dense"
        env_cfg.variant.adaptive_phase_stage1 = bool(variant.adaptive_phase_stage1)
    if stage == 2:
        start_episodes_at_zero(env_cfg)
    return env_cfg


def seed_everything(seed: int) -> None:
    import random

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def pin_observation_stats(env, normalizers, keep_values: bool = False) -> None:
    """Holds the columns the env names (TrackingEnv.pinned_observation_stats) fixed in `normalizers`,
    at the env's values or, with `keep_values`, at the ones they hold."""
    for columns, mean, var in env.pinned_observation_stats():
        for normalizer in normalizers:
            normalizer.pin(columns, None if keep_values else mean, None if keep_values else var)


def train_stage1(data, env_cfg, cfg: TrainConfig, run_dir: str | Path, *, resume: bool = False, env=None,
                 iterations: int | None = None, time_limit_s: float | None = None, chunk_s: float | None = None,
                 go_states: dict | None = None, handoff=None, **trainer_kwargs) -> dict:
    """Stage 1 with `cfg.algorithm`'s trainer. `chunk_s`: stop after about this long, resumable (Trainer.run)."""
    variant: Variant = cfg.variant_spec
    seed_everything(cfg.seed)
    env = env if env is not None else make_env(data, env_cfg, cfg, stage=1, go_states=go_states, handoff=handoff)
    phase_rate = phase_rate_of(env, data)
    if cfg.algorithm == "fast_td3":
        from pipeline.rl.fast_td3 import build_fast_td3_trainer

        trainer = build_fast_td3_trainer(env, data, cfg, run_dir, phase_rate, **trainer_kwargs)
        if time_limit_s is None and cfg.time_limit_stage1_s > 0:
            time_limit_s = cfg.time_limit_stage1_s
        return trainer.run(cfg.iterations_stage1 if iterations is None else iterations, resume=resume,
                           time_limit_s=time_limit_s, chunk_s=chunk_s)
    net = cfg.network
    policy = Stage1Policy(env.spec().actor_obs_dim, env.spec().action_dim, net.actor_hidden, net.activation, net.init_log_std,
                          adaptive_phase=variant.adaptive_phase_stage1, phase_rate=phase_rate, normalize_obs=cfg.ppo.normalize_obs)
    critic = DoubleCritic(env.spec().critic_obs_dim, net.critic_hidden, net.activation, cfg.ppo.normalize_obs)
    pin_observation_stats(env, [policy.normalizer, critic.normalizer])
    amp, amp_ref = None, None
    if variant.amp != "none":
        amp_ref = reference_windows(data.motion.joint_pos, cfg.amp.window, variant.amp == "mimic")
        amp = AMPDiscriminator(amp_ref.shape[1], cfg.amp, net.activation)
    meta = policy_meta(env, data, cfg, 1, phase_rate)
    trainer = Trainer(env, policy, critic, cfg, run_dir, stage=1, meta=meta, l2c2=True, amp=amp, amp_reference=amp_ref,
                      use_phase_offset=variant.adaptive_phase_stage1, **trainer_kwargs)
    if time_limit_s is None and cfg.time_limit_stage1_s > 0:
        time_limit_s = cfg.time_limit_stage1_s
    return trainer.run(cfg.iterations_stage1 if iterations is None else iterations, resume=resume,
                       time_limit_s=time_limit_s, chunk_s=chunk_s)


def train_stage2(data, env_cfg, cfg: TrainConfig, run_dir: str | Path, *, stage1_dir: str | Path, resume: bool = False,
                 env=None, iterations: int | None = None, time_limit_s: float | None = None, chunk_s: float | None = None,
                 go_states: dict | None = None, handoff=None, **trainer_kwargs) -> dict:
    variant: Variant = cfg.variant_spec
    stage1_dir = Path(stage1_dir)
    if not (stage1_dir / "config.json").is_file():
        raise PipelineInputError(stage1_dir, None, "stage 2 needs a stage-1 policy here (config.json + model.safetensors); train stage 1 first")
    seed_everything(cfg.seed + 1)
    env = env if env is not None else make_env(data, env_cfg, cfg, stage=2, go_states=go_states, handoff=handoff)
    phase_rate = phase_rate_of(env, data)
    expect = policy_meta(env, data, cfg, 1, phase_rate)
    base, base_meta = load_policy(stage1_dir, expect)
    if int(base_meta["stage"]) != 1:
        raise PipelineInputError(stage1_dir, "stage", f"expected a stage-1 policy, got stage {base_meta['stage']}")
    net = cfg.network
    policy = Stage2Policy(base, net.adapter_hidden, net.activation, net.adapter_init_log_std,
                          freeze_base=variant.freeze_stage1, phase_rate=phase_rate, normalize_obs=cfg.ppo.normalize_obs)
    critic = DoubleCritic(env.spec().critic_obs_dim, net.critic_hidden, net.activation, cfg.ppo.normalize_obs)
    pin_observation_stats(env, [policy.normalizer, critic.normalizer])
    # An unfrozen base keeps the scale it was trained with: its pinned columns stay where they are.
    pin_observation_stats(env, [base.normalizer], keep_values=True)
    meta = policy_meta(env, data, cfg, 2, phase_rate, freeze_base=variant.freeze_stage1)
    meta["architecture"]["actor_hidden"] = base_meta["architecture"]["actor_hidden"]
    meta["architecture"]["adaptive_phase"] = base_meta["architecture"].get("adaptive_phase", False)
    # A stage-1 actor from the off-policy trainer is deterministic (bounded mean): the adapters shape its mean.
    meta["architecture"]["output_bound"] = base_meta["architecture"].get("output_bound", 0.0)
    meta["stage1_algorithm"] = base_meta.get("algorithm", "ppo")
    trainer = Trainer(env, policy, critic, cfg, run_dir, stage=2, meta=meta, l2c2=False, use_phase_offset=True, **trainer_kwargs)
    if time_limit_s is None and cfg.time_limit_stage2_s > 0:
        time_limit_s = cfg.time_limit_stage2_s
    return trainer.run(cfg.iterations_stage2 if iterations is None else iterations, resume=resume,
                       time_limit_s=time_limit_s, chunk_s=chunk_s)


def train(data, env_cfg, cfg: TrainConfig, run_dir: str | Path, *, resume: bool = False, **kwargs) -> dict:
    """Both stages as the variant asks: run_dir/stage1, run_dir/stage2; returns the last stage's metrics."""
    run_dir = Path(run_dir)
    s1_metrics_file = run_dir / "stage1" / "metrics.json"
    if resume and s1_metrics_file.is_file() and (run_dir / "stage1" / "policy" / "config.json").is_file():
        metrics = json.loads(s1_metrics_file.read_text())  # stage 1 already finished
    else:
        metrics = train_stage1(data, env_cfg, cfg, run_dir / "stage1", resume=resume, **kwargs)
        if metrics.get("paused"):  # a chunk (chunk_s) ended inside stage 1: the next resume goes on there
            return metrics
    if cfg.variant_spec.stage2:
        metrics = train_stage2(data, env_cfg, cfg, run_dir / "stage2", stage1_dir=run_dir / "stage1" / "policy",
                               resume=resume, **kwargs)
    return metrics
