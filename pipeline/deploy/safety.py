"""The controller's modes and the watchdog that can send it to damping at any tick.

Modes: DAMPING (start, kp = 0) → RAMP (measured pose → default pose, timed) → STAND (the balance
policy holds the robot; the go, a key or --go, counts after `stand_s`) → POLICY (the task) → STAND
(the balance policy again, until Ctrl-C or for `hold_after_s`) → exit in DAMPING. A fault (LowState older
than `state_timeout_s`, a joint outside its range by more than `joint_margin_rad`, base tilt beyond
`max_tilt_rad`) or Ctrl-C sends it to DAMPING and ends the run; nothing ever holds the last policy
target.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from pipeline.common.errors import PipelineInputError


class Mode(enum.Enum):
    DAMPING = "damping"
    RAMP = "ramp"
    STAND = "stand"
    POLICY = "policy"


@dataclass(frozen=True)
class SafetyConfig:
    damping_s: float = 1.0  # damping at the start, before the ramp
    ramp_s: float = 3.0  # measured pose → default pose
    stand_s: float = 2.0  # the balance policy holds the robot at least this long before a go counts
    hold_after_s: float | None = None  # the balance policy after the episode for this long, then damping and
    #                                    exit; None: until Ctrl-C (a robot left standing, not sinking)
    state_timeout_s: float = 0.1  # LowState older than this → damping
    joint_margin_rad: float = 0.1  # measured joint beyond its limit by more than this → damping
    max_tilt_rad: float = 1.2  # base tilt (angle of gravity from the base's -z) beyond this → damping
    damping_kd_scale: float = 1.0  # damping kd = this × the export's kd, kp = 0
    first_state_timeout_s: float = 5.0  # no LowState at all within this → exit

    def __post_init__(self):
        for key in ("damping_s", "ramp_s", "stand_s", "hold_after_s", "damping_kd_scale"):
            if getattr(self, key) is not None and not getattr(self, key) >= 0:
                raise PipelineInputError("deploy", f"safety.{key}", f"must be >= 0, got {getattr(self, key)}")
        for key in ("state_timeout_s", "first_state_timeout_s", "joint_margin_rad", "max_tilt_rad"):
            if not getattr(self, key) > 0:
                raise PipelineInputError("deploy", f"safety.{key}", f"must be > 0, got {getattr(self, key)}")
        if self.max_tilt_rad >= np.pi:
            raise PipelineInputError("deploy", "safety.max_tilt_rad", "must be below pi")


@dataclass(frozen=True)
class Measured:
    """What one LowState says, in the policy's joint order."""

    joint_pos: np.ndarray
    joint_vel: np.ndarray
    gravity: np.ndarray  # projected gravity (3,)
    base_ang_vel: np.ndarray
    age_s: float  # now − when it was received


class Watchdog:
    def __init__(self, config: SafetyConfig, joint_limits: np.ndarray, joint_names):
        self.config = config
        self.limits = np.asarray(joint_limits)
        self.lower = self.limits[:, 0] - config.joint_margin_rad
        self.upper = self.limits[:, 1] + config.joint_margin_rad
        self.joint_names = list(joint_names)
        self.cos_max_tilt = float(np.cos(config.max_tilt_rad))

    def past_limit(self, joint_pos: np.ndarray) -> float:
        """How far (rad) the measured joint furthest outside its range is past it (0 inside)."""
        return max(0.0, float(np.max(np.maximum(self.limits[:, 0] - joint_pos, joint_pos - self.limits[:, 1]))))

    def fault(self, measured: Measured) -> str | None:
        """The reason to fall back to damping now, or None."""
        if measured.age_s > self.config.state_timeout_s:
            return f"LowState stopped: none for {measured.age_s:.3f} s (limit {self.config.state_timeout_s} s)"
        outside = np.flatnonzero((measured.joint_pos < self.lower) | (measured.joint_pos > self.upper))
        if outside.size:
            j = int(outside[0])
            return (f"joint {self.joint_names[j]} at {measured.joint_pos[j]:+.3f} rad left its range "
                    f"[{self.lower[j]:+.3f}, {self.upper[j]:+.3f}] (limits ± margin)")
        g = np.asarray(measured.gravity, dtype=np.float64)
        cos_tilt = -g[2] / max(float(np.linalg.norm(g)), 1e-9)
        if cos_tilt < self.cos_max_tilt:
            return (f"base tilted {np.degrees(np.arccos(np.clip(cos_tilt, -1, 1))):.0f} deg "
                    f"(limit {np.degrees(self.config.max_tilt_rad):.0f} deg)")
        return None


def ramp_targets(start: np.ndarray, goal: np.ndarray, elapsed_s: float, duration_s: float) -> np.ndarray:
    """Linear interpolation start → goal over `duration_s` (goal from then on)."""
    a = 1.0 if duration_s <= 0 else float(np.clip(elapsed_s / duration_s, 0.0, 1.0))
    return (1 - a) * np.asarray(start) + a * np.asarray(goal)


def clamp_targets(targets: np.ndarray, joint_limits: np.ndarray) -> np.ndarray:
    """The ramp's targets inside the joints' ranges. The policies' targets are sent as they trained:
    they press past a range (a landing's ankles, by up to 2.8 rad of target) for the torque that
    holds the joint at its stop; clamped, the same policy falls (measured on the bridge)."""
    return np.clip(targets, joint_limits[:, 0], joint_limits[:, 1])
