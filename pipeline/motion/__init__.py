"""Reference motions: the `Motion` type, forward kinematics, and on-disk datasets."""

from pipeline.motion.motion import Motion, RobotKinematics

__all__ = ["Motion", "RobotKinematics"]
