"""Odometry as a pluggable input: the base position in the frame the robot stood in at the go.

The paper's robot gets it from lidar odometry at ~10 Hz. A source is either a callable returning
the world (x, y, z) position and yaw, or a DDS topic of nav_msgs Odometry_ (what a lidar-odometry
node publishes; the sim bridge publishes the simulated pelvis on one). The policy samples it at the
export's `rate_hz` and holds it in between (`PolicyStepper`), as in training.
"""

from __future__ import annotations

from typing import Callable, Protocol

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.export.policy_step import rotate_z


class PoseSource(Protocol):
    def pose(self) -> tuple[np.ndarray, float] | None:
        """World position (3,) and yaw (rad), or None while nothing has arrived."""


class CallablePose:
    def __init__(self, fn: Callable[[], tuple[np.ndarray, float] | None]):
        self.fn = fn

    def pose(self):
        return self.fn()


class TopicPose:
    """The newest nav_msgs Odometry_ on a topic of a `DdsLink`."""

    def __init__(self, link, topic: str):
        from pipeline.deploy.transport import CheckedReader

        self.topic = topic
        self.reader = CheckedReader(link.reader(topic, link.types.Odometry), None)

    def pose(self):
        received = self.reader.poll()
        if received is None:
            return None
        p, q = received.message.pose.pose.position, received.message.pose.pose.orientation
        yaw = float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))
        return np.array([p.x, p.y, p.z], dtype=np.float64), yaw


class Odometry:
    """Position relative to the pose at `start()`, rotated into the start heading (as in sim2sim)."""

    def __init__(self, source: PoseSource):
        self.source = source
        self.origin: tuple[np.ndarray, float] | None = None

    def start(self) -> None:
        pose = self.source.pose()
        if pose is None:
            raise RuntimeError("odometry: no pose received yet, cannot set the start frame")
        self.origin = pose

    def read(self) -> np.ndarray:
        pose = self.source.pose()
        if pose is None or self.origin is None:
            raise RuntimeError("odometry: no pose received")
        return rotate_z(pose[0] - self.origin[0], -self.origin[1])


def require_odometry(needs: bool, source, policy_json: str) -> Odometry | None:
    """The odometry of a `PoseSource` or a callable returning (position, yaw); an error naming the
    observation term when the policy observes odometry and nothing provides it."""
    if needs and source is None:
        raise PipelineInputError(policy_json, "observation.terms",
                                 "the policy observes odometry; give --odometry-topic (nav_msgs Odometry_) "
                                 "or an odometry callable")
    if source is not None and not hasattr(source, "pose"):
        source = CallablePose(source)
    return Odometry(source) if source is not None else None
