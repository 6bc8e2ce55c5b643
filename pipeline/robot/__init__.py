"""The Unitree G1 model: configuration table, MjSpec builder, terrain hook."""

from pipeline.robot.g1 import RobotConfig, build_model, build_spec, load_robot_config

__all__ = ["RobotConfig", "build_model", "build_spec", "load_robot_config"]
