"""Joint targets that let the G1's PD actuators produce a reference motion's own torques.

A position actuator applies τ = Kp (q* − q) − Kd q̇. Aimed at the reference's joints (q* = q_ref) it
leaves two errors that a tracking policy would otherwise have to learn to cancel at every step:
  * the damping term brakes every fast motion: Kd/Kp = 2ζ/ω, 64 ms of lag for the G1's gains, i.e.
    0.6 rad on a knee extending at 10 rad/s in a push-off;
  * nothing holds the robot up against gravity or drives the reference's accelerations, so the
    soft gains (10 Hz) sag the crouch and never reach the take-off speed.
With the feedforward target

    q* = q_ref + (Kd q̇_ref + τ_ref) / Kp

the actuator applies Kp (q_ref − q) + Kd (q̇_ref − q̇) + τ_ref: a PD on both position and velocity
errors plus the reference's joint torques. τ_ref is the reference's inverse dynamics
(`robot/dynamics.py`: the base carried by the feet on the ground, the joints supplying the rest),
clipped to the motors' effort limits.

On the shared far jump, replaying the reference open-loop (a zero action) around these targets crosses
the take-off keyframe 0.15 m from it and lands 0.24 m short; around the bare reference joints the
robot sags 0.37 m low by the take-off and falls before the landing (benchmarks/RESULTS.md).
"""

from __future__ import annotations

import mujoco
import numpy as np

from pipeline.motion.feet import detect_foot_contacts
from pipeline.motion.motion import Motion
from pipeline.robot.dynamics import joint_torques
from pipeline.robot.g1 import RobotConfig, load_robot_config


def reference_joint_torques(motion: Motion, robot: RobotConfig | None = None,
                            model: mujoco.MjModel | None = None) -> np.ndarray:
    """(T, J) joint torques (N·m) that produce `motion` with its base carried by the feet on the ground
    (`motion/feet.py`, the contacts the keyframe stage finds take-offs and landings with, so a foot on a
    box carries too), clipped to the motors' effort limits."""
    robot = robot or load_robot_config()
    torques = joint_torques(motion, detect_foot_contacts(motion), robot, model)
    return np.clip(torques, -robot.effort_limit, robot.effort_limit)


def feedforward_joint_targets(motion: Motion, robot: RobotConfig | None = None,
                              model: mujoco.MjModel | None = None) -> np.ndarray:
    """(T, J) q_ref + (Kd q̇_ref + τ_ref) / Kp: the actuator targets at a zero action (module docstring).
    `motion`'s joints in the robot's order (`zero_action_targets` puts them there)."""
    robot = robot or load_robot_config()
    torques = reference_joint_torques(motion, robot, model)
    return motion.joint_pos + (robot.kd * motion.joint_vel + torques) / robot.kp


def zero_action_targets(motion: Motion, action_offset: str, robot: RobotConfig | None = None,
                        model: mujoco.MjModel | None = None) -> np.ndarray | None:
    """(T, J) per-frame joint targets of a zero action for `EnvConfig.action_offset` ("reference":
    the reference's joints; "feedforward": `feedforward_joint_targets`); None for "default", whose
    target is the standing pose at every frame. Joints in the robot's (action) order. The env and the
    exported graph both read this table."""
    if action_offset == "default":
        return None
    robot = robot or load_robot_config()
    if tuple(motion.joint_names) != tuple(robot.joint_names):
        motion = motion.reorder_joints(robot.joint_names)
    if action_offset == "reference":
        return np.asarray(motion.joint_pos)
    if action_offset == "feedforward":
        return feedforward_joint_targets(motion, robot, model)
    raise ValueError(f"unknown action_offset {action_offset!r}")
