"""The reward side of `EnvConfig` (`env.rewards`): the paper's weights and kernel widths, the regularisation
penalties and their curriculum. The balance env's rewards share the penalties (balance_config.py)."""

from __future__ import annotations

from dataclasses import dataclass, field

LOWER_BODY = ("pelvis", "left_hip", "left_knee", "left_ankle", "right_hip", "right_knee", "right_ankle")


@dataclass
class PenaltyWeights:
    """The regularisers every env pays in its dense group (`robot_env.PENALTY_TERMS`)."""

    feet_orientation: float = -0.05
    joint_acc: float = -2.5e-7
    joint_vel: float = -5e-4
    action_rate: float = -0.5
    smoothness: float = -0.01
    torques: float = -1e-6
    torque_limits: float = -1.0
    joint_pos_limits: float = -10.0
    joint_vel_limits: float = -5.0


@dataclass
class RewardWeights(PenaltyWeights):
    # sparse group: paid only on the step that crosses a keyframe (termination: on the terminal step)
    global_body_pos: float = 10.0
    global_body_rot: float = 5.0
    global_feet_pos: float = 10.0
    termination: float = -200.0
    # dense group: every step
    local_body_pos: float = 0.75
    local_body_rot: float = 0.5
    local_joint_pos: float = 0.75
    # Not in the paper's table (0 = off): the root's tilt (gravity in the pelvis frame) and angular
    # velocity against the reference's, every step, as BeyondMimic's anchor terms. The local terms above
    # are all relative to the root, so the pelvis's own pitch is otherwise paid for only at keyframes.
    # Off: at 1.0 / 0.5 the far jump's robot (learn_cpu --segment 2.3) braked after its landing as the reference
    # does, then sat back and fell backward (0.016 against 0.094), and on the bundled sample half the episodes
    # fell before the landing (benchmarks/RESULTS.md, commit 9018155).
    root_tilt: float = 0.0
    root_ang_vel: float = 0.0
    # sparse, when the phase ends alive (0 = off): upright and slow there, where the balance policy takes the
    # robot over (export/chain.py), as skill chaining makes one skill end inside the next one's starting set
    handoff: float = 0.0
    # sparse, at the chain's handoff (> 0: episodes end there, not at the phase's end): this weight times the
    # balance policy's own estimate of catching the robot in the state it is handed (envs/handoff_catch.py)
    handoff_catch: float = 0.0


@dataclass
class KernelSigmas:
    """σ² of the exp(−Σ err²/(n σ²)) tracking kernels (the reference implementation's values, but
    `feet_pos`)."""

    upper_body_pos: float = 0.03
    # 0.1 m² pays 0.98 of the term for feet 11 cm off; 0.01 taught learn_cpu's 2.3 s far jump to stand from the
    # reference's touch-down, not from t = 0 (benchmarks/RESULTS.md, commit 9018155)
    lower_body_pos: float = 0.1
    body_rot: float = 1.0
    joint_pos: float = 1.0
    # 0.3 m², ten times the reference's 0.03: a landing keyframe missed by 0.5 m still pays exp(−0.83) = 0.43
    # of the feet term instead of 0.0002, so the sparse return tells a near miss from a far one and pulls the
    # jump towards the edited landing. On learn_cpu (seeds 0, 2, 3) 0.906 / 0.938 / 0.922 against 0.938 /
    # 0.891 / 0.859, the 1.7–2.0 m gaps 0.70 / 0.60 / 0.60 against 0.60 / 0.30 / 0.20
    # (benchmarks/RESULTS.md, commit 8523f33).
    feet_pos: float = 0.3
    root_tilt: float = 0.1  # |Δ gravity_xy|², unitless: 0.3 off (a 17° lean) pays exp(−0.9) = 0.41
    handoff_tilt: float = 0.05  # |g_xy|² at the handoff: a 13° lean pays exp(−1)
    handoff_speed: float = 0.25  # (m/s)² of the base's horizontal speed at the handoff
    root_ang_vel: float = 4.0  # |Δω|² in (rad/s)²: 2 rad/s off pays exp(−1) = 0.37


@dataclass
class PenaltyCurriculum:
    """Scale on the dense group's penalty terms (every negative weight), adapted to how often the
    policy falls, as HumanoidVerse/ASAP's reward-penalty curriculum (the code base AdaMimic's reward
    table comes from) adapts it to episode length. Why: the dense group has no termination penalty,
    so while the exploration noise alone costs more in action rate (~4/step at std 0.4 over 27
    joints) than local tracking pays (at most 2), every step alive lowers the dense return and the
    dense critic teaches the policy to fall. A schedule by training progress raised the penalties on
    a policy that still fell in 70 % of its episodes and drove the dense return to -80.
    Training starts at `initial`; at each curriculum update (one per PPO iteration) the scale shrinks
    by the factor (1 - `rate`) when more than `fall_rate_high` of the episodes finished since the
    last update were terminated (a fall or a lost keyframe), and grows by (1 + `rate`) when fewer
    than `fall_rate_low` were, within [`initial`, 1]. Outside training (no curriculum call) the scale is 1: the paper's weights."""

    enabled: bool = True
    initial: float = 0.1
    fall_rate_high: float = 0.5
    fall_rate_low: float = 0.3
    rate: float = 0.05

    def next_scale(self, scale: float, fall_rate: float) -> float:
        """The scale after one update, given the share of the finished episodes that were terminated."""
        if fall_rate > self.fall_rate_high:
            scale *= 1.0 - self.rate
        elif fall_rate < self.fall_rate_low:
            scale *= 1.0 + self.rate
        return min(max(scale, self.initial), 1.0)


@dataclass
class PenaltyConfig:
    """What every env's penalties read besides their weights."""

    feet: list[str] = field(default_factory=lambda: ["left_ankle", "right_ankle"])
    soft_torque_limit: float = 0.95  # fraction of the effort limit where the torque penalty starts
    soft_joint_pos_limit: float = 0.95  # fraction of the joint range (about its centre)
    soft_joint_vel_limit: float = 0.95
    # Multiply the dense group by the control dt (legged_gym / IsaacLab / HumanoidVerse habit). It does
    # not change learning here: PPO normalises each group's advantages and the critics their returns.
    scale_by_dt: bool = False
    penalty_curriculum: PenaltyCurriculum = field(default_factory=PenaltyCurriculum)


@dataclass
class RewardConfig(PenaltyConfig):
    weights: RewardWeights = field(default_factory=RewardWeights)
    sigma2: KernelSigmas = field(default_factory=KernelSigmas)
    lower_body: list[str] = field(default_factory=lambda: list(LOWER_BODY))
