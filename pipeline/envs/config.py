"""`EnvConfig`: every number of the tracking environment, typed, from `params.yaml` `env:`.

`EnvConfig.from_dict(raw, where="env")` accepts a partial mapping (missing keys keep the paper's
defaults below) and raises `PipelineInputError` naming the dotted key for unknown keys, wrong types
and out-of-range values, so a typo in params.yaml is caught before anything runs.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from pipeline.common.errors import PipelineInputError
from pipeline.common.typed_config import replace_from_mapping
from pipeline.envs.falls import SUCCESS_THRESHOLD_M
from pipeline.envs.go_starts import GoStartConfig
from pipeline.envs.reward_config import RewardConfig

ACTION_OFFSETS = ("feedforward", "reference", "default")  # what a zero action aims the joints at (EnvConfig)


@dataclass
class ObservationConfig:
    history: int = 5
    odometry_rate_hz: float = 10.0
    odometry_noise_std: float = 0.02  # m, Gaussian, per axis, at each refresh
    # How the networks' normalisers scale the ψ input. "samples": fixed at the mean and variance of the
    # task's ψ samples, the range the policy is asked to cover. "running": by its running statistics, as
    # every other input; the ψ curriculum keeps its worlds within ~0.1 m of ψ_raw for most of a run, so
    # ψ's running std ends near 0.08 m and the far jump's 0.2 m and 2.0 m gaps reach the networks at
    # about ±7 normalised units, where training never went. On learn_cpu (same prior, seeds 0–2)
    # "samples" read 0.938 / 0.938 / 0.891 against 0.797 / 0.875 / 0.938, every 0.2–0.5 m gap cleared
    # at each seed (benchmarks/RESULTS.md, commit b822369).
    psi_scale: str = "samples"


@dataclass
class CurriculumConfig:
    """Keyframe-error termination threshold against training progress p ∈ [0, 1]: linear from
    `start` down to `min` over [0, tighten_until], held, then relaxed linearly to `max` over
    [relax_from, 1] (the paper relaxes it late in training)."""

    start: float = 1.5
    min: float = 0.6
    max: float = 2.0
    tighten_until: float = 0.5
    relax_from: float = 0.8
    # What is compared with the threshold at a keyframe: "max" — the worst tracked body's position
    # error; "mean" — the bodies' mean, the quantity that E_g-bpe and the success test measure. "max"
    # ends most far-jump training episodes on the head's error after the landing, but those episodes
    # fall anyway when it is loosened, and "mean" scored no better (benchmarks/RESULTS.md, commit 645cc71).
    measure: str = "max"

    def threshold_at(self, progress: float) -> float:
        """The threshold (m) at training progress `progress` (clamped to [0, 1])."""
        p = min(max(float(progress), 0.0), 1.0)
        if p <= self.tighten_until:
            return self.start + (self.min - self.start) * (p / self.tighten_until if self.tighten_until > 0 else 1.0)
        if p < self.relax_from:
            return self.min
        return self.min + (self.max - self.min) * ((p - self.relax_from) / max(1.0 - self.relax_from, 1e-6))


@dataclass
class TerminationConfig:
    """Falls end an episode. With `relative_to_reference` (default) both fall checks are measured
    against the reference at the current frame, because dynamic clips themselves cross the absolute
    thresholds: the far-jump crouch has the pelvis at |g_xy| = 0.75 (0.8 would end an episode that
    follows the reference closely within 4 steps) and its landing puts the pelvis at 0.43 m.
      tilt:   |g_xy(robot) − g_xy(reference)| > max_tilt   (absolute: |g_xy(robot)| > max_tilt)
      height: z < min(min_base_height, z_reference − base_height_margin)   (absolute: z < min_base_height)
    For a reference that stands upright above min_base_height + margin both equal the absolute checks."""

    keyframe_error: CurriculumConfig = field(default_factory=CurriculumConfig)
    max_tilt: float = 0.8  # |projected gravity xy| (of the error against the reference by default)
    min_base_height: float = 0.4  # m, world z of the pelvis
    base_height_margin: float = 0.25  # m the pelvis may sink below the reference's before it counts as a fall
    relative_to_reference: bool = True
    base_height_enabled: bool = True
    base_height_exempt_tasks: list[str] = field(default_factory=list)  # tasks that go low on purpose


@dataclass
class Range:
    enabled: bool = True
    low: float = 0.0
    high: float = 0.0


def _rng(enabled: bool, low: float, high: float):
    return field(default_factory=lambda: Range(enabled, low, high))


@dataclass
class PushConfig:
    enabled: bool = True
    interval_s: list[float] = field(default_factory=lambda: [5.0, 10.0])
    max_vel_xy: float = 0.5  # m/s added to the base velocity
    max_vel_yaw: float = 0.4  # rad/s


@dataclass
class RandomizationConfig:
    """The paper's domain randomisation table; each term switchable. Applied per world at reset."""

    enabled: bool = True
    trunk_mass_add: Range = _rng(True, -2.0, 5.0)  # kg added to `trunk_body`
    base_com_offset: Range = _rng(True, -0.1, 0.1)  # m, per axis, on `base_body`
    link_mass_scale: Range = _rng(True, 0.9, 1.1)  # every other body
    friction: Range = _rng(True, 0.1, 1.1)  # sliding friction of the robot's collision geoms
    friction_combine: str = "average"  # "average" with the ground's, as PhysX (Isaac Gym) does, or "robot"
    restitution: Range = _rng(True, 0.0, 0.1)  # via the feet's contact damping ratio
    p_gain_scale: Range = _rng(True, 0.85, 1.15)
    d_gain_scale: Range = _rng(True, 0.85, 1.15)
    motor_strength: Range = _rng(True, 0.9, 1.1)
    control_delay_ms: Range = _rng(True, 0.0, 100.0)
    push: PushConfig = field(default_factory=PushConfig)
    trunk_body: str = "torso_link"
    base_body: str = "pelvis"


@dataclass
class VariantConfig:
    tracking: str = "sparse"  # "sparse": keyframe rewards (AdaMimic); "dense": every-step global tracking
    adaptive_phase_stage1: bool = False  # the trainer feeds Δφ^Δ already in stage 1


@dataclass
class SamplingConfig:
    """How a reset picks the edited sample (ψ) to track (pipeline/envs/sampling.py)."""

    # "uniform" | "adaptive": in proportion to each sample's running failure rate | "curriculum": each
    # world climbs levels of growing |ψ − ψ_raw| as its episodes succeed | "sweep": every sample in turn
    # (what evaluation uses)
    # Why curriculum: on benchmarks/learn_cpu.py (20 min, 2 seeds each, the same 128 evaluation episodes)
    # it scored 0.58 and 0.47 from t = 0 against uniform draws' 0.41 and 0.36.
    mode: str = "curriculum"
    uniform_ratio: float = 0.2  # adaptive: share of draws that stay uniform
    rate: float = 0.05  # adaptive: EMA step of a sample's failure rate per finished episode
    levels: int = 8  # curriculum: groups of samples by edit size (fewer samples: one level each)
    # curriculum: levels per side of ψ_raw, each world on one side (worlds shared out by the sides'
    # sample counts). Pooled, a level holds a short and a far gap of the same |ψ − ψ_raw|; at the end
    # of a far-jump run every level succeeds 40–50 % while the far gaps read 0–10 % in evaluation
    # and the short ones 75–100 %, so the walk says nothing about the far side. Opt-in: split, the far
    # side's rates fall 0.53 -> 0 with ψ as they should, but learn_cpu read the same (0.781 / 0.656
    # against 0.859 / 0.594 pooled, both with relax_from 0.6; benchmarks/RESULTS.md, commit 30dbea0).
    split_sides: bool = False
    # curriculum: which falls send a world one level down. "every_fall": any failed episode (legged_gym's
    # rule). "relative": only where the world's level succeeds at most `relative_ratio` times as often as
    # the bottom level (the clip's own neighbourhood): falls that happen as often at the bottom come from
    # the randomisation and the exploration noise, not from the edit. `relative`, `judge: success_test`
    # and `uniform_share` are opt-in: on learn_cpu they read within the default's seed spread, because
    # the far jump's training episodes succeed 1–15 % at every level until the keyframe-error threshold
    # relaxes, and no rule climbs on that (benchmarks/RESULTS.md, commit 30dbea0).
    demotion: str = "every_fall"
    relative_ratio: float = 0.8
    level_rate: float = 0.02  # EMA step of each level's success rate per recorded episode
    # curriculum: share of draws taken uniformly over all samples instead of from the world's level, so the
    # levels the walk has not reached are still met now and then (0: none, legged_gym's rule)
    uniform_share: float = 0.0
    # curriculum and adaptive: what makes an episode that met the edit a failure. "termination": any
    # termination. "success_test": the evaluation's test, a fall or a keyframe whose body-mean error is
    # over `success_threshold_m`; an episode that the keyframe-error termination (a training device,
    # tighter than the test mid-run) ended with every keyframe so far within the test is left out:
    # nothing says it would have failed (mid-run that termination ends about half of the episodes).
    judge: str = "termination"
    success_threshold_m: float = SUCCESS_THRESHOLD_M  # the evaluation's (evaluate.success_threshold_m)


@dataclass
class OwnStateStartConfig:
    """Episodes restarted from states the policy itself reached (pipeline/envs/own_states.py).

    Reference-state starts put the robot exactly on the clip. A policy that lands a jump 0.3 m ahead of
    the reference, pitched forward and still moving has met its own landing only once per episode from
    t = 0, and the episodes are lost in the second after it (benchmarks/RESULTS.md, commits f8efea5–ab5803e).
    With `prob` > 0 the env keeps a ring of the last `capacity` states of episodes that started before
    the keyframes labelled `at_label` (their own flight, not a reference start) as they crossed one
    alive, and a reset starts there with probability `prob`: the same physics state, ψ sample, phase
    and observation history. Off by default: on learn_cpu's 2.3 s far-jump segment, 0.3 read 0.000 against
    0.094 without it (benchmarks/RESULTS.md, commit c101d09). Evaluation and stage 2 always start at t = 0.
    """

    prob: float = 0.0
    at_label: str = "landing"  # keyframe labels that start with it, as the keyframe stage writes them
    capacity: int = 512


@dataclass
class StartFrameSamplingConfig:
    """Where reference-state starts begin (pipeline/envs/start_frames.py): `uniform` over the stance
    frames, or `adaptive` — groups of frames drawn in proportion to how often episodes started there
    fail, with `uniform_share` of the draws kept uniform. `rate_smoothing`: the weight of each step's
    ended episodes in a group's running failure rate. Off by default: on learn_cpu's 2.3 s far-jump segment it
    taught the stand from the reference's own touch-down (18 of 18 episodes started there, 0 of 18 without it)
    but not from t = 0, where the robot's own touch-down is not the reference's (benchmarks/RESULTS.md, commit 9018155)."""

    mode: str = "uniform"
    bins: int = 16
    uniform_share: float = 0.3
    rate_smoothing: float = 0.05


def start_episodes_at_zero(cfg) -> None:
    """Switches off every start after t = 0 (reference-state and own-state starts), in place: evaluation
    scores every keyframe and stage 2 learns from the clip's beginning. Duck-typed, so a config without
    these fields passes through."""
    if hasattr(cfg, "rsi_prob"):
        cfg.rsi_prob = 0.0
    if hasattr(cfg, "own_state_starts"):
        cfg.own_state_starts.prob = 0.0


@dataclass
class EnvConfig:
    rewards: RewardConfig = field(default_factory=RewardConfig)
    observations: ObservationConfig = field(default_factory=ObservationConfig)
    terminations: TerminationConfig = field(default_factory=TerminationConfig)
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    variant: VariantConfig = field(default_factory=VariantConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    rsi_prob: float = 0.5  # probability of a reference-state start instead of t = 0
    # Where those starts are drawn: "stance" — any frame outside the flights (between a takeoff and the
    # next landing keyframe), as DeepMimic's uniform-phase RSI; "keyframes" — keyframe frames only.
    # Why stance: with keyframe starts alone nothing started inside a push-off (the far jump has no
    # keyframe between its crouch and its takeoff), and policies learnt to stand up and hop instead
    # of jumping. Flights are left out because an edited landing may be out of reach from a state of
    # the unedited flight.
    rsi_frames: str = "stance"
    # Uniform noise (±) added to the base's velocity at a reference-state start, as BeyondMimic and mjlab's
    # tracking task perturb their starts: linear (m/s, world x y z) and angular (rad/s, base frame, as
    # MuJoCo's free joint stores it).
    # Exact reference states teach recovery from nowhere but the reference: a policy that lands a jump a
    # little fast or pitched forward has never been there. Off by default: in 8 minutes on the sample it
    # did not help (benchmarks/RESULTS.md); it is there for longer runs.
    rsi_lin_vel_noise: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    rsi_ang_vel_noise: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # The same for the pose, as BeyondMimic's reset does: the base turned about its own x, y, z axes by up
    # to ± these angles (rad; a rotation vector), each joint moved by up to ± rsi_joint_pos_noise (rad, kept
    # inside its limits), then the base lifted or lowered so that the lowest tracked foot is as high as the
    # reference's. Why: a policy trained from exact reference states stands only from states very near
    # them: after the far jump's landing, its own pose (3 cm lower, 0.08 off in sideways lean, legs 0.02-0.15 rad
    # off) falls where the reference's pose with its own velocities stands. Off by default: one 640-iteration
    # run with it did not stand either (benchmarks/RESULTS.md, commit 1a1474d); it is there for longer runs.
    rsi_root_rot_noise: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    rsi_joint_pos_noise: float = 0.0
    rsi_sampling: StartFrameSamplingConfig = field(default_factory=StartFrameSamplingConfig)
    own_state_starts: OwnStateStartConfig = field(default_factory=OwnStateStartConfig)
    go_starts: GoStartConfig = field(default_factory=GoStartConfig)  # envs/go_starts.py
    # Joint targets = offset + action_scale · action. "feedforward": the reference's joints at the frame
    # the step ends on, plus the PD actuators' feedforward (Kd q̇_ref + τ_ref) / Kp so that a zero action
    # produces the reference's own torques (envs/feedforward.py); "reference": the reference's joints
    # alone; "default": the standing default pose, as the paper and BeyondMimic. Around the default pose
    # a zero action stands the robot up out of the far jump's crouch, and within 20 CPU minutes policies
    # never found the push-off (0 % success from t = 0, benchmarks/RESULTS.md); around the bare
    # reference joints the soft gains sag the crouch and brake the push-off, so the policy first has
    # to learn to cancel its own actuators. The exported graph adds the offset itself (export/onnx_export.py).
    action_offset: str = "feedforward"
    action_clip: float = 100.0
    # Physics preset of robots/g1/robot.yaml `physics.presets` (docs/physics.md): "baseline", the reference
    # every published figure was measured with; "light" (3 of the 7 capsules under each foot collide), 1.3-1.7
    # times the env steps per second and as close to baseline as baseline's own timestep error; "fast"
    # (also 10 ms substeps, 2 per control step), 2.1-2.8 times, but policies' falls after a landing came
    # out differently under it: for quick runs, not for figures compared with baseline's.
    physics: str = "baseline"
    physics_threads: int = 2
    torch_threads: int = 1  # 0: leave torch's setting alone; small per-step ops prefer 1 beside physics
    # torch.compile the step's rewards, terminations and observations into fused kernels. For GPUs,
    # where the eager step's ~450 kernel launches cost more host time than the physics; on the CPU the
    # eager step already runs at ~0.9 of bare MuJoCo and compiling costs a minute at start-up.
    compile: bool = False

    @classmethod
    def from_dict(cls, raw: dict | None, where: str = "env") -> "EnvConfig":
        cfg = replace_from_mapping(cls(), raw or {}, where)
        cfg.validate(where)
        return cfg

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def validate(self, where: str = "env") -> None:
        def bad(key, problem):
            raise PipelineInputError(where, key, problem)

        if self.observations.history < 1:
            bad("observations.history", "must be >= 1")
        if self.observations.odometry_rate_hz <= 0:
            bad("observations.odometry_rate_hz", "must be > 0")
        if self.observations.odometry_noise_std < 0:
            bad("observations.odometry_noise_std", "must be >= 0")
        if self.observations.psi_scale not in ("running", "samples"):
            bad("observations.psi_scale", f"must be 'running' or 'samples', got {self.observations.psi_scale!r}")
        if not 0.0 <= self.rsi_prob <= 1.0:
            bad("rsi_prob", "must be in [0, 1]")
        if self.rsi_frames not in ("stance", "keyframes"):
            bad("rsi_frames", f"must be 'stance' or 'keyframes', got {self.rsi_frames!r}")
        for key in ("rsi_lin_vel_noise", "rsi_ang_vel_noise", "rsi_root_rot_noise"):
            value = getattr(self, key)
            if len(value) != 3 or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not v >= 0 for v in value):
                bad(key, f"must be three numbers >= 0 (x, y, z), got {value!r}")
        if not self.rsi_joint_pos_noise >= 0:  # a number already: from_dict's typed conversion checks that
            bad("rsi_joint_pos_noise", f"must be >= 0 (rad), got {self.rsi_joint_pos_noise!r}")
        rs = self.rsi_sampling
        if rs.mode not in ("uniform", "adaptive"):
            bad("rsi_sampling.mode", f"{rs.mode!r}: expected 'uniform' or 'adaptive'")
        if rs.bins < 1:
            bad("rsi_sampling.bins", "must be >= 1")
        if not 0.0 <= rs.uniform_share <= 1.0:
            bad("rsi_sampling.uniform_share", "must be in [0, 1]")
        if not 0.0 < rs.rate_smoothing <= 1.0:
            bad("rsi_sampling.rate_smoothing", "must be in (0, 1]")
        if not 0.0 <= self.own_state_starts.prob <= 1.0:
            bad("own_state_starts.prob", "must be in [0, 1]")
        if self.own_state_starts.capacity < 1:
            bad("own_state_starts.capacity", "must be >= 1")
        if not self.own_state_starts.at_label:
            bad("own_state_starts.at_label", "must name a keyframe label, e.g. 'landing'")
        self.go_starts.validate(where)
        if self.action_offset not in ACTION_OFFSETS:
            bad("action_offset", f"must be one of {', '.join(ACTION_OFFSETS)}, got {self.action_offset!r}")
        if self.sampling.mode not in ("uniform", "adaptive", "curriculum", "sweep"):
            bad("sampling.mode", f"must be 'uniform', 'adaptive', 'curriculum' or 'sweep', got {self.sampling.mode!r}")
        if self.sampling.levels < 2:
            bad("sampling.levels", "must be >= 2")
        if not 0.0 <= self.sampling.uniform_ratio <= 1.0:
            bad("sampling.uniform_ratio", "must be in [0, 1]")
        if not 0.0 < self.sampling.rate <= 1.0:
            bad("sampling.rate", "must be in (0, 1]")
        if self.sampling.demotion not in ("every_fall", "relative"):
            bad("sampling.demotion", f"must be 'every_fall' or 'relative', got {self.sampling.demotion!r}")
        if not 0.0 < self.sampling.relative_ratio <= 1.0:
            bad("sampling.relative_ratio", "must be in (0, 1]")
        if not 0.0 < self.sampling.level_rate <= 1.0:
            bad("sampling.level_rate", "must be in (0, 1]")
        if not 0.0 <= self.sampling.uniform_share <= 1.0:
            bad("sampling.uniform_share", "must be in [0, 1]")
        if self.sampling.judge not in ("termination", "success_test"):
            bad("sampling.judge", f"must be 'termination' or 'success_test', got {self.sampling.judge!r}")
        if not self.sampling.success_threshold_m > 0.0:
            bad("sampling.success_threshold_m", "must be > 0")
        if self.variant.tracking not in ("sparse", "dense"):
            bad("variant.tracking", f"must be 'sparse' or 'dense', got {self.variant.tracking!r}")
        for name, value in dataclasses.asdict(self.rewards.sigma2).items():
            if value <= 0:
                bad(f"rewards.sigma2.{name}", "must be > 0")
        c = self.terminations.keyframe_error
        if not (0 < c.min <= c.start <= c.max):
            bad("terminations.keyframe_error", "needs 0 < min <= start <= max")
        if not (0 <= c.tighten_until <= c.relax_from <= 1):
            bad("terminations.keyframe_error", "needs 0 <= tighten_until <= relax_from <= 1")
        if c.measure not in ("max", "mean"):
            bad("terminations.keyframe_error.measure", f"must be 'max' or 'mean', got {c.measure!r}")
        for f in dataclasses.fields(RandomizationConfig):
            r = getattr(self.randomization, f.name)
            if isinstance(r, Range) and r.low > r.high:
                bad(f"randomization.{f.name}", f"low {r.low} > high {r.high}")
        if self.randomization.friction_combine not in ("average", "robot"):
            bad("randomization.friction_combine", f"must be 'average' or 'robot', got {self.randomization.friction_combine!r}")
        if self.randomization.control_delay_ms.low < 0:
            bad("randomization.control_delay_ms.low", "must be >= 0")
        iv = self.randomization.push.interval_s
        if len(iv) != 2 or not 0 < iv[0] <= iv[1]:
            bad("randomization.push.interval_s", "must be [min, max] seconds with 0 < min <= max")
        pc = self.rewards.penalty_curriculum
        if not 0.0 < pc.initial <= 1.0:
            bad("rewards.penalty_curriculum.initial", "must be in (0, 1]")
        if not 0.0 <= pc.fall_rate_low <= pc.fall_rate_high <= 1.0:
            bad("rewards.penalty_curriculum", "needs 0 <= fall_rate_low <= fall_rate_high <= 1")
        if not 0.0 <= pc.rate < 1.0:
            bad("rewards.penalty_curriculum.rate", "must be in [0, 1)")
        if self.terminations.max_tilt <= 0:
            bad("terminations.max_tilt", "must be > 0")
        if self.terminations.base_height_margin < 0:
            bad("terminations.base_height_margin", "must be >= 0")
        from pipeline.robot.g1 import load_robot_config

        presets = load_robot_config().physics_presets
        if self.physics not in presets:
            bad("physics", f"unknown physics preset {self.physics!r} (robots/g1/robot.yaml physics.presets: "
                f"{', '.join(presets)})")
        if self.physics_threads < 1:
            bad("physics_threads", "must be >= 1")
        if self.torch_threads < 0:
            bad("torch_threads", "must be >= 0")
