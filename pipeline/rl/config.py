"""Typed training configuration (`params.yaml` -> `train:`), two size profiles and the variants.

`TrainConfig.from_dict(raw)` starts from the profile named in `raw["profile"]` (default `cpu`) and
overrides any field given; unknown keys and unknown variants raise `PipelineInputError` naming the key.

Profiles:
  * `gpu`: the paper's appendix (4096 envs, 75 steps/iteration, 5 epochs, [512, 256, 128] ELU, ...).
  * `cpu`: the same algorithm sized so one stage takes a few minutes on 2 cores.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from pipeline.common.errors import PipelineInputError
from pipeline.common.typed_config import replace_from_mapping


@dataclass(frozen=True)
class Variant:
    """What a method (or ablation) of the paper's main table trains on and how.

    reference: which TrackingData the env tracks: "edit" (D_edit, keyframe targets),
               "rule" (D_rule, rule-edited dense reference) or "original" (the unedited motion).
    keyframe_rewards: sparse keyframe rewards (AdaMimic) vs dense global tracking every step (DeepMimic).
    stage2: train the phase and tracking adapters after stage 1.
    freeze_stage1: keep the stage-1 policy fixed in stage 2 (False: fine-tune it with the adapters).
    adaptive_phase_stage1: the stage-1 policy also outputs the phase-rate offset Δφ^Δ.
    amp: "none", "style" (discriminator on joint windows) or "mimic" (discriminator also sees the phase).
    """

    name: str
    reference: str
    keyframe_rewards: bool
    stage2: bool
    freeze_stage1: bool = True
    adaptive_phase_stage1: bool = False
    amp: str = "none"


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("adamimic", "edit", True, stage2=True),
        Variant("adamimic_stage1", "edit", True, stage2=False),
        Variant("adamimic_stage1_dphi", "edit", True, stage2=False, adaptive_phase_stage1=True),
        Variant("adamimic_nofreeze", "edit", True, stage2=True, freeze_stage1=False),
        Variant("adamimic_dense", "rule", False, stage2=True),
        Variant("deepmimic_noadapt", "original", False, stage2=False),
        Variant("deepmimic_adapt", "rule", False, stage2=False),
        Variant("deepmimic_adapt_dphi", "rule", False, stage2=False, adaptive_phase_stage1=True),
        Variant("amp_style", "edit", True, stage2=False, amp="style"),
        Variant("amp_mimic", "edit", True, stage2=False, amp="mimic"),
    )
}


def get_variant(name: str, where: str = "train") -> Variant:
    if name not in VARIANTS:
        raise PipelineInputError(where, "variant", f"unknown variant {name!r}; known: {', '.join(VARIANTS)}")
    return VARIANTS[name]


@dataclass
class NetworkConfig:
    actor_hidden: list[int] = field(default_factory=lambda: [512, 256, 128])
    critic_hidden: list[int] = field(default_factory=lambda: [512, 256, 128])
    activation: str = "elu"
    init_log_std: float = 0.0  # exp(0) = 1: std of the Gaussian over normalised actions
    # Stage-2 adapters (each its own MLP); a^Δ's last layer starts at zero so stage 2 starts at stage 1.
    adapter_hidden: list[int] = field(default_factory=lambda: [256, 128])
    adapter_init_log_std: float = -1.0


@dataclass
class PPOConfig:
    num_envs: int = 4096
    steps_per_iteration: int = 75
    epochs: int = 5
    minibatches: int = 4
    clip: float = 0.2
    entropy_coef: float = 0.01
    value_coef: float = 1.0
    value_clip: bool = False  # clipping at 0.2 would crawl on sparse returns of order 100
    learning_rate: float = 1e-3
    adaptive_lr: bool = True
    kl_target: float = 0.01
    lr_min: float = 1e-5
    lr_max: float = 1e-2
    max_grad_norm: float = 1.0
    gamma_sparse: float = 1.0
    gamma_dense: float = 0.99
    lam: float = 0.95
    adv_weight_sparse: float = 1.0
    adv_weight_dense: float = 0.5
    normalize_obs: bool = True
    # L2C2 (Kobayashi 2022): penalise output change between an observation and a random point on the
    # segment to the next observation. Stage 1 only, as in the paper.
    l2c2_actor: float = 1.0
    l2c2_critic: float = 0.1
    # Share of each minibatch the L2C2 terms are estimated on (a random subset: the minibatch is a
    # slice of a random permutation). Their extra forward and backward passes are ~40 % of a stage-1
    # update on the CPU; a subset gives the same expected penalty for less.
    l2c2_fraction: float = 1.0
    # Exploration noise per world as an AR(1) process with this coefficient per step (pipeline/rl/exploration.py);
    # each step's noise stays N(0, 1), so PPO's log-probabilities are unchanged. 0: white noise, the paper's.
    noise_correlation: float = 0.0


@dataclass
class FastTD3Config:
    """The off-policy trainer (pipeline/rl/fast_td3.py): many worlds feed a large replay buffer,
    large batches, clipped double Q per reward group, normalised observations, a deterministic actor
    explored with per-world Gaussian noise."""

    num_envs: int = 4096
    steps_per_iteration: int = 8        # env steps of every world per iteration (curricula, logs, saves)
    updates_per_step: int = 2           # critic updates after each env step of all worlds
    policy_delay: int = 2               # one actor update every this many critic updates
    batch_size: int = 32768
    buffer_size: int = 1_048_576        # transitions kept (all worlds together)
    learning_starts: int = 4            # env steps of every world before the first update
    n_step: int = 3                     # n-step TD targets (cut at episode ends)
    gamma_sparse: float = 1.0           # as PPO's: the keyframe group's episodic return
    gamma_dense: float = 0.99
    # PPO bootstraps the dense group at timeouts. TrackingEnv's timeouts are the clip's end (phase 1): a
    # state no stored transition starts from, so its Q is never regressed and an off-policy bootstrap
    # would feed its arbitrary value to every state before it. Off: a timeout ends both groups' returns.
    bootstrap_dense_timeouts: bool = False
    tau: float = 0.1                    # Polyak rate of the target critics
    actor_learning_rate: float = 3e-4
    critic_learning_rate: float = 3e-4
    weight_decay: float = 0.1           # AdamW, both nets
    max_grad_norm: float = 0.0          # 0: no clipping
    # Exploration: each world draws its noise std uniformly in [min, max] at every episode start (mixed noise).
    exploration_std_min: float = 0.05
    exploration_std_max: float = 0.6
    target_noise: float = 0.2           # target policy smoothing: std and clip of the noise on the next action
    target_noise_clip: float = 0.5
    action_bound: float = 3.0           # raw actions kept in ±bound (tanh-scaled in the actor)
    # Each group's rewards times its scale are what its critics regress (returns near unit size).
    reward_scale_sparse: float = 0.01
    reward_scale_dense: float = 0.01
    # Actor loss −Σ_g w_g·Q_g, each Q in its group's scaled reward units.
    q_weight_sparse: float = 1.0
    q_weight_dense: float = 0.5
    mirror: bool = False                # left-right mirror augmentation of replayed samples (pipeline/rl/mirror.py)
    # Store the replay buffer in checkpoints: resume is then exact. Off, a resumed run refills
    # `learning_starts` steps before updating again (smaller checkpoints, not bit-identical).
    checkpoint_buffer: bool = True


@dataclass
class AMPConfig:
    window: int = 5  # joint-position frames per discriminator sample
    style_weight: float = 0.1
    task_weight: float = 0.9
    hidden: list[int] = field(default_factory=lambda: [256, 128])
    learning_rate: float = 1e-4
    grad_penalty: float = 5.0
    batch_size: int = 4096


@dataclass
class TrainConfig:
    profile: str = "cpu"
    # Stage 1's trainer: "ppo" (the paper's double-critic PPO) or "fast_td3" (off-policy, pipeline/rl/fast_td3.py).
    # Stage 2's adapters always train with PPO, on a stage-1 actor from either.
    algorithm: str = "ppo"
    variant: str = "adamimic"
    seed: int = 0
    device: str = "cpu"
    backend: str = "cpu"
    iterations_stage1: int = 300  # 0: train until the stage's time limit
    iterations_stage2: int = 150
    # Optional wall-clock caps (seconds, 0 = none): a stage stops at its iteration count or its cap,
    # whichever comes first. The curricula follow the iteration count (wall time only when it is 0), so
    # a run is the same on any machine unless the cap stops it, which it then reports.
    time_limit_stage1_s: float = 0.0
    time_limit_stage2_s: float = 0.0
    save_interval: int = 25
    keep_checkpoints: int = 2
    # The policy written at the end of a stage: 0 = the last iteration's weights; f > 0 = the mean of the
    # policy's weights (normalisers included) taken every `average_every` iterations over the last f of
    # the stage (pipeline/rl/averaging.py). Opt-in: on learn_cpu it read about a run's median snapshot, not
    # always more than its last one (benchmarks/RESULTS.md, commit 136f1b8).
    average_tail: float = 0.0
    average_every: int = 10
    ppo: PPOConfig = field(default_factory=PPOConfig)
    fast_td3: FastTD3Config = field(default_factory=FastTD3Config)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    amp: AMPConfig = field(default_factory=AMPConfig)

    @property
    def variant_spec(self) -> Variant:
        return get_variant(self.variant)

    def num_envs(self, stage: int = 1) -> int:
        """Worlds the stage's trainer steps (stage 2 is always PPO)."""
        return self.fast_td3.num_envs if stage == 1 and self.algorithm == "fast_td3" else self.ppo.num_envs

    def steps_per_iteration(self, stage: int = 1) -> int:
        return self.fast_td3.steps_per_iteration if stage == 1 and self.algorithm == "fast_td3" else self.ppo.steps_per_iteration

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, raw: dict | None, where: str = "train") -> "TrainConfig":
        raw = dict(raw or {})
        profile = raw.get("profile", "cpu")
        if profile not in PROFILES:
            raise PipelineInputError(where, "profile", f"unknown profile {profile!r}; known: {', '.join(PROFILES)}")
        cfg = replace_from_mapping(PROFILES[profile](), raw, where)
        get_variant(cfg.variant, where)
        _validate(cfg, where)
        return cfg


ALGORITHMS = ("ppo", "fast_td3")


def _validate(cfg: TrainConfig, where: str) -> None:
    if cfg.algorithm not in ALGORITHMS:
        raise PipelineInputError(where, "algorithm", f"unknown algorithm {cfg.algorithm!r}; known: {', '.join(ALGORITHMS)}")
    if cfg.algorithm == "fast_td3" and cfg.variant_spec.amp != "none":
        raise PipelineInputError(where, "algorithm", f"variant {cfg.variant!r} (AMP) trains with ppo only")
    p, q = cfg.ppo, cfg.fast_td3
    checks = [
        (q.num_envs > 0, "fast_td3.num_envs", "must be > 0"),
        (q.steps_per_iteration > 0, "fast_td3.steps_per_iteration", "must be > 0"),
        (q.updates_per_step >= 0, "fast_td3.updates_per_step", "must be >= 0"),
        (q.policy_delay >= 1, "fast_td3.policy_delay", "must be >= 1"),
        (q.batch_size > 0, "fast_td3.batch_size", "must be > 0"),
        (q.n_step >= 1, "fast_td3.n_step", "must be >= 1"),
        (q.learning_starts >= q.n_step, "fast_td3.learning_starts", "must be >= n_step"),
        (q.buffer_size >= q.num_envs * (q.learning_starts + 1), "fast_td3.buffer_size",
         "must hold at least num_envs * (learning_starts + 1) transitions"),
        (0.0 < q.gamma_sparse <= 1.0, "fast_td3.gamma_sparse", "must be in (0, 1]"),
        (0.0 < q.gamma_dense <= 1.0, "fast_td3.gamma_dense", "must be in (0, 1]"),
        (0.0 < q.tau <= 1.0, "fast_td3.tau", "must be in (0, 1]"),
        (q.actor_learning_rate > 0 and q.critic_learning_rate > 0, "fast_td3.actor_learning_rate", "learning rates must be > 0"),
        (0.0 <= q.exploration_std_min <= q.exploration_std_max, "fast_td3.exploration_std_min", "must be in [0, exploration_std_max]"),
        (q.action_bound > 0, "fast_td3.action_bound", "must be > 0"),
        (q.reward_scale_sparse > 0 and q.reward_scale_dense > 0, "fast_td3.reward_scale_sparse", "reward scales must be > 0"),
        (p.num_envs > 0, "ppo.num_envs", "must be > 0"),
        (p.steps_per_iteration > 0, "ppo.steps_per_iteration", "must be > 0"),
        (p.epochs > 0, "ppo.epochs", "must be > 0"),
        (0.0 < p.l2c2_fraction <= 1.0, "ppo.l2c2_fraction", "must be in (0, 1]"),
        (0.0 <= p.noise_correlation < 1.0, "ppo.noise_correlation", "must be in [0, 1) (0: white noise)"),
        (0 < p.minibatches <= p.num_envs * p.steps_per_iteration, "ppo.minibatches", "must be in [1, envs*steps]"),
        (0.0 < p.gamma_sparse <= 1.0, "ppo.gamma_sparse", "must be in (0, 1]"),
        (0.0 < p.gamma_dense <= 1.0, "ppo.gamma_dense", "must be in (0, 1]"),
        (0.0 <= p.lam <= 1.0, "ppo.lam", "must be in [0, 1]"),
        (p.learning_rate > 0, "ppo.learning_rate", "must be > 0"),
        (cfg.iterations_stage1 >= 0, "iterations_stage1", "must be >= 0"),
        (cfg.iterations_stage2 >= 0, "iterations_stage2", "must be >= 0"),
        (cfg.iterations_stage1 > 0 or cfg.time_limit_stage1_s > 0, "iterations_stage1", "0 trains until time_limit_stage1_s: set it > 0"),
        (cfg.iterations_stage2 > 0 or cfg.time_limit_stage2_s > 0, "iterations_stage2", "0 trains until time_limit_stage2_s: set it > 0"),
        (cfg.time_limit_stage1_s >= 0, "time_limit_stage1_s", "must be >= 0 (0 = no limit)"),
        (cfg.time_limit_stage2_s >= 0, "time_limit_stage2_s", "must be >= 0 (0 = no limit)"),
        (cfg.save_interval > 0, "save_interval", "must be > 0"),
        (cfg.keep_checkpoints >= 1, "keep_checkpoints", "must be >= 1"),
        (0.0 <= cfg.average_tail <= 1.0, "average_tail", "must be in [0, 1] (0: the last iteration's weights)"),
        (cfg.average_every >= 1, "average_every", "must be >= 1"),
        (cfg.network.activation in ACTIVATIONS, "network.activation", f"one of {sorted(ACTIVATIONS)}"),
        (cfg.amp.window >= 2, "amp.window", "must be >= 2"),
        (all(h > 0 for h in cfg.network.actor_hidden + cfg.network.critic_hidden), "network", "layer sizes > 0"),
    ]
    for ok, key, problem in checks:
        if not ok:
            raise PipelineInputError(where, key, problem)


ACTIVATIONS = {"elu", "relu", "tanh", "silu"}


def gpu_profile() -> TrainConfig:
    """The paper's appendix values (fast_td3: FastTD3's humanoid sizes)."""
    # fast_td3: its defaults; the buffer (~4 GB at 4096 worlds) stays out of checkpoints (docs/trainers.md).
    return TrainConfig(profile="gpu", device="cuda", backend="warp", iterations_stage1=3000,
                       iterations_stage2=1500, save_interval=100, fast_td3=FastTD3Config(checkpoint_buffer=False))


def cpu_profile() -> TrainConfig:
    """Same algorithm for 2 cores: fewer envs, smaller nets, a few minutes per stage."""
    return TrainConfig(
        profile="cpu",
        iterations_stage1=300,
        iterations_stage2=150,
        save_interval=25,
        # L2C2 on a quarter of each minibatch: the update was half of stage 1's time on 2 cores, and the
        # full L2C2 ~40 % of it. learn_cpu read 0.594-0.656 over three seeds with it, 0.578-0.594 without.
        ppo=PPOConfig(num_envs=192, steps_per_iteration=24, epochs=5, minibatches=4, l2c2_fraction=0.25),
        # Initial std 0.5 (of normalised actions, i.e. ~0.2 rad on the legs): with std 1 the noise alone
        # makes about half the reference-start episodes fall before the policy has learnt anything.
        network=NetworkConfig(actor_hidden=[256, 128, 64], critic_hidden=[256, 128, 64], adapter_hidden=[128, 64],
                              init_log_std=-0.7),
        amp=AMPConfig(hidden=[128, 64], batch_size=1024),
        # Same worlds and steps per iteration as PPO's (the same env steps per iteration, so the curricula
        # move alike). One critic update of 1024 samples per env step of all worlds: about the network
        # passes of a PPO iteration (4608 samples x 5 epochs), each sample replayed about as often.
        fast_td3=FastTD3Config(num_envs=192, steps_per_iteration=24, updates_per_step=1, batch_size=1024,
                               buffer_size=98_304, learning_starts=8),
    )


PROFILES = {"cpu": cpu_profile, "gpu": gpu_profile}
