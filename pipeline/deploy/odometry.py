"""Odometry as a pluggable input: the base position in the frame the robot stood in at the go.

The paper's robot gets it from lidar odometry at ~10 Hz. A source is either a callable returning
the world (x, y, z) position and yaw, or a DDS topic of nav_msgs Odometry_ (what a lidar-odometry
node publishes; the sim bridge publishes the simulated pelvis on one). The policy samples it at the
export's `rate_hz` and holds it in between (`PolicyStepper`), as in training.
"""

from __future__ import annotations

import time
from typing import Callable, Protocol

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.export.policy_step import rotate_z, yaw_of


class PoseSource(Protocol):
    def pose(self) -> tuple[np.ndarray, float] | None:
        """World position (3,) and yaw (rad), or None while nothing has arrived."""


class CallablePose:
    def __init__(self, fn: Callable[[], tuple[np.ndarray, float] | None]):
        self.fn = fn

    def pose(self):
        return self.fn()


class TopicPose:
    """The newest nav_msgs Odometry_ on a topic of a `DdsLink`, while it is fresh: a pose older than
    `max_age_s` (five periods of 10 Hz lidar odometry) reads as none, so a frozen odometry node sends
    the controller to damping instead of feeding the policy a held position."""

    def __init__(self, link, topic: str, max_age_s: float = 0.5):
        from pipeline.deploy.transport import CheckedReader

        self.topic, self.max_age_s = topic, max_age_s
        self.reader = CheckedReader(link.reader(topic, link.types.Odometry), None)

    def pose(self):
        received = self.reader.poll()
        if received is None or time.monotonic() - received.time > self.max_age_s:
            return None
        p, q = received.message.pose.pose.position, received.message.pose.pose.orientation
        return np.array([p.x, p.y, p.z], dtype=np.float64), yaw_of((q.w, q.x, q.y, q.z))


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
            raise RuntimeError("odometry: no pose received, or none fresh")
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
