"""Datasets on disk in the LeRobot v3.0 layout (see `pipeline.dataset.lerobot`)."""

from pipeline.dataset.lerobot import Feature, LeRobotData, read_dataset, write_dataset

__all__ = ["Feature", "LeRobotData", "read_dataset", "write_dataset"]
