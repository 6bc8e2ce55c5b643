"""The 29-DoF G1's motor order and the mapping of an exported policy's joints onto it.

The `unitree_hg` messages carry 35 motor slots; a 29-DoF G1 uses the first 29 in Unitree's published G1 joint order
(`pipeline.motion.importers.UNITREE_G1_29DOF_JOINTS`, also the column order of the common G1 CSV). Our model locks the waist roll and pitch (the policy has 27
joints), so those two motors are commanded to stay at zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.motion.importers import UNITREE_G1_29DOF_JOINTS

NUM_MOTOR_SLOTS = 35
G1_MOTOR_NAMES = UNITREE_G1_29DOF_JOINTS  # the SDK's motor order
NUM_MOTORS = len(G1_MOTOR_NAMES)
LOCKED_AT_ZERO = ("waist_roll_joint", "waist_pitch_joint")
# the locked joints are held with the gains of the nearest driven joint of the same actuator type
LOCKED_GAINS_FROM = "waist_yaw_joint"


@dataclass(frozen=True)
class MotorMap:
    """policy joint j ↔ motor `motor_of_joint[j]`; `locked` motors are held at q = 0."""

    joint_names: tuple[str, ...]
    motor_of_joint: np.ndarray  # (J,) motor index of each policy joint
    locked: np.ndarray  # motor indices held at zero
    locked_gain_joint: int  # the policy joint whose kp/kd hold the locked motors

    @classmethod
    def from_joint_names(cls, joint_names, source: str = "policy.json") -> "MotorMap":
        names = tuple(joint_names)
        unknown = [n for n in names if n not in G1_MOTOR_NAMES]
        if unknown:
            raise PipelineInputError(source, "joint_names", f"not motors of the 29-DoF G1: {unknown}")
        if len(set(names)) != len(names):
            raise PipelineInputError(source, "joint_names", "a joint is listed twice")
        missing = [n for n in G1_MOTOR_NAMES if n not in names and n not in LOCKED_AT_ZERO]
        if missing:
            raise PipelineInputError(source, "joint_names", f"G1 motors the policy does not drive: {missing}")
        if LOCKED_GAINS_FROM not in names:
            raise PipelineInputError(source, "joint_names", f"{LOCKED_GAINS_FROM} is needed for the locked waist")
        motor = np.array([G1_MOTOR_NAMES.index(n) for n in names])
        locked = np.array([G1_MOTOR_NAMES.index(n) for n in LOCKED_AT_ZERO if n not in names], dtype=int)
        return cls(names, motor, locked, names.index(LOCKED_GAINS_FROM))

    def to_motors(self, per_joint: np.ndarray, locked_value: float) -> np.ndarray:
        """(J,) values in policy order → (29,) in motor order, `locked_value` on the locked motors."""
        out = np.full(NUM_MOTORS, float(locked_value))
        out[self.motor_of_joint] = per_joint
        return out

    def from_motors(self, per_motor: np.ndarray) -> np.ndarray:
        """(≥29,) values in motor order → (J,) in policy order."""
        return np.asarray(per_motor)[self.motor_of_joint]
