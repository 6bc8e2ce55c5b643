"""`BalanceEnvConfig`: every number of the balance env, typed, from `params.yaml` `balance.env:`.

The shared parts (randomisation, pushes, penalties, physics, threads) are the tracking env's own
dataclasses; only the rewards, the falls, the episode and the starts are the balance task's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from pipeline.common.errors import PipelineInputError
from pipeline.common.typed_config import replace_from_mapping
from pipeline.envs.config import PushConfig, RandomizationConfig
from pipeline.envs.reward_config import PenaltyConfig, PenaltyWeights


@dataclass
class BalanceRewardWeights(PenaltyWeights):
    # dense group, each an exp(−err²/σ²) kernel in [0, 1]
    upright: float = 1.0  # |g_xy|: the pelvis upright
    base_height: float = 0.5  # pelvis height against the stance's
    lin_vel: float = 1.0  # base velocity in the horizontal plane: still
    ang_vel: float = 0.5  # base angular velocity: still
    default_pose: float = 0.5  # joints at the default pose
    stance: float = 0.5  # each foot under the pelvis where the stance puts it: steps back into the stance
    # the heading the episode started with: a chain's task starts facing where the robot stood (0: off)
    heading: float = 0.0
    # sparse group: a fall (the only event of the task)
    termination: float = -200.0
    # gentler than the tracking task's -0.5: a balance policy has to move fast when pushed
    action_rate: float = -0.1


@dataclass
class BalanceSigmas:
    upright: float = 0.05  # |g_xy|²: a 13° lean pays exp(−1)
    base_height: float = 0.01  # m²: 10 cm low pays exp(−1)
    lin_vel: float = 0.25  # (m/s)²
    ang_vel: float = 1.0  # (rad/s)²
    default_pose: float = 0.1  # mean rad² over the joints
    stance: float = 0.01  # m², each foot's horizontal offset in the pelvis's heading frame
    heading: float = 0.05  # rad², the turn from the start's heading: 13° pays exp(−1)


@dataclass
class BalanceRewardConfig(PenaltyConfig):
    weights: BalanceRewardWeights = field(default_factory=BalanceRewardWeights)
    sigma2: BalanceSigmas = field(default_factory=BalanceSigmas)


@dataclass
class BalanceObservationConfig:
    history: int = 5


@dataclass
class FallConfig:
    """Absolute fall checks (`falls.fall_flags`): the pelvis tilted past `max_tilt` (|g_xy|) or lower
    than `min_base_height` above the ground."""

    max_tilt: float = 0.8
    min_base_height: float = 0.4


@dataclass
class BalanceStartConfig:
    """Where episodes start: the stance at rest plus noise, or a state from the start-state files
    (`pipeline/balance/starts.py`: the task policies' own end-of-task states), or the stance lowered
    from a little above the floor, as a robot is lowered off its gantry."""

    states_prob: float = 0.4  # share of starts from the recorded states (when there are any)
    drop_prob: float = 0.1  # share of starts from up to `drop_height` above the stance
    drop_height: float = 0.08  # m
    joint_pos_noise: float = 0.1  # rad, uniform ±, each joint (stance starts)
    lin_vel_noise: float = 0.3  # m/s, uniform ±, horizontal (stance starts)
    ang_vel_noise: float = 0.3  # rad/s, uniform ±, each axis (stance starts)
    state_vel_scale: list[float] = field(default_factory=lambda: [0.8, 1.1])  # recorded states' velocities × U


@dataclass
class BalanceCurriculum:
    """How hard training starts: the pushes' speed, the control delays and the share of recorded starts
    grow linearly from `initial` of the configured values at the start of training to all of them at
    `until` (a fraction of the run). Outside training (no curriculum call) everything is at full value."""

    initial: float = 0.0
    until: float = 0.4

    def level(self, progress: float) -> float:
        if self.until <= 0:
            return 1.0
        return min(1.0, self.initial + (1.0 - self.initial) * max(progress, 0.0) / self.until)


def _balance_randomization() -> RandomizationConfig:
    # the pushes: base velocity kicks up to 0.5 m/s every 1-3 s
    return RandomizationConfig(push=PushConfig(interval_s=[1.0, 3.0], max_vel_xy=0.5, max_vel_yaw=0.4))


ARM_JOINTS = tuple(f"{side}_{joint}_joint" for side in ("left", "right") for joint in (
    "shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch", "wrist_yaw"))


@dataclass
class BalanceEnvConfig:
    # Joints the policy does not move: held at the stance (their action is scaled by 0, in the env and the
    # exported graph alike). The arms by default: legs and waist balance, and 14 fewer noisy outputs.
    frozen_joints: list[str] = field(default_factory=lambda: list(ARM_JOINTS))
    # A zero action aims the joints at the default pose plus the torques that hold it still, divided by
    # Kp (envs/feedforward.py's idea at the stance): the soft 10 Hz gains otherwise sag the pose forward,
    # and the robot falls from the stance in 1.3 s instead of 2.5 s without any policy.
    stance_feedforward: bool = True
    rewards: BalanceRewardConfig = field(default_factory=BalanceRewardConfig)
    observations: BalanceObservationConfig = field(default_factory=BalanceObservationConfig)
    terminations: FallConfig = field(default_factory=FallConfig)
    randomization: RandomizationConfig = field(default_factory=_balance_randomization)
    starts: BalanceStartConfig = field(default_factory=BalanceStartConfig)
    curriculum: BalanceCurriculum = field(default_factory=BalanceCurriculum)
    episode_s: float = 10.0
    physics: str = "baseline"
    physics_threads: int = 2
    torch_threads: int = 1
    compile: bool = False
    action_clip: float = 100.0

    @classmethod
    def from_dict(cls, raw: dict | None, where: str = "balance.env") -> "BalanceEnvConfig":
        cfg = replace_from_mapping(cls(), raw or {}, where)
        cfg.validate(where)
        return cfg

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def validate(self, where: str = "balance.env") -> None:
        def bad(key, problem):
            raise PipelineInputError(where, key, problem)

        from pipeline.robot.g1 import load_robot_config

        unknown = sorted(set(self.frozen_joints) - set(load_robot_config().joint_names))
        if unknown:
            bad("frozen_joints", f"unknown joints {unknown}")
        if self.observations.history < 1:
            bad("observations.history", "must be >= 1")
        if not self.episode_s > 0:
            bad("episode_s", "must be > 0")
        s = self.starts
        if not (0.0 <= s.states_prob <= 1.0 and 0.0 <= s.drop_prob <= 1.0 and s.states_prob + s.drop_prob <= 1.0):
            bad("starts", "states_prob and drop_prob must be in [0, 1] and add up to at most 1")
        for key in ("drop_height", "joint_pos_noise", "lin_vel_noise", "ang_vel_noise"):
            if getattr(s, key) < 0:
                bad(f"starts.{key}", "must be >= 0")
        if len(s.state_vel_scale) != 2 or not 0 <= s.state_vel_scale[0] <= s.state_vel_scale[1]:
            bad("starts.state_vel_scale", "must be [low, high] with 0 <= low <= high")
        if not (0.0 <= self.curriculum.initial <= 1.0 and 0.0 <= self.curriculum.until <= 1.0):
            bad("curriculum", "initial and until must be in [0, 1]")
        for name, value in dataclasses.asdict(self.rewards.sigma2).items():
            if value <= 0:
                bad(f"rewards.sigma2.{name}", "must be > 0")
        if self.terminations.max_tilt <= 0:
            bad("terminations.max_tilt", "must be > 0")
        iv = self.randomization.push.interval_s
        if len(iv) != 2 or not 0 < iv[0] <= iv[1]:
            bad("randomization.push.interval_s", "must be [min, max] seconds with 0 < min <= max")
        if self.physics not in load_robot_config().physics_presets:
            bad("physics", f"unknown physics preset {self.physics!r}")
        if self.physics_threads < 1:
            bad("physics_threads", "must be >= 1")
