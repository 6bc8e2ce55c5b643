"""The fall checks and the standing test: one definition for the envs (torch), the evaluation, sim2sim,
the push prior's rollouts, `rehearse` and the deploy watchdog (numpy). Every function here is plain
array arithmetic, so it takes torch tensors and numpy arrays alike.

  fell by tilt:    |tilt_xy|² > max_tilt²   (tilt_xy: the projected gravity's x, y, or its error against a reference)
  fell by height:  base height < min_height
  standing:        |g_xy| < `STANDING.max_tilt`, pelvis ≥ `STANDING.min_height` above the ground under it,
                   base speed < `STANDING.max_speed`, that ground within `STANDING.max_ground_offset` of the
                   ground the reference ends on, no fall check fired before.
"""

from __future__ import annotations

from dataclasses import dataclass

# An episode succeeds (the paper's test) when every keyframe is crossed with the tracked bodies' mean
# world error within this distance (m). Every judge reads it from here.
SUCCESS_THRESHOLD_M = 1.0


def fall_flags(tilt_xy, base_height, max_tilt, min_height):
    """(by_tilt, by_height): the tilt (..., 2) past `max_tilt`, the base below `min_height` (None: no check)."""
    by_tilt = (tilt_xy**2).sum(-1) > max_tilt**2
    by_height = base_height < min_height if min_height is not None else by_tilt & False
    return by_tilt, by_height


@dataclass(frozen=True)
class StandingTest:
    """Upright, high and still, where the task ends: what `rest_to_rest` asks of the robot at the end of its chain."""

    max_tilt: float = 0.3  # |projected gravity xy| (sin of the lean: 17°)
    min_height: float = 0.55  # m, pelvis above the ground under it
    max_speed: float = 0.2  # m/s, the base's linear speed
    # m between the ground under the pelvis and the ground under the reference's last keyframe: a step up
    # that lands in front of the step and stands there has not done the task (the smallest step is 5 cm)
    max_ground_offset: float = 0.02

    def __call__(self, gravity_xy, height_above_ground, base_speed, ground_offset=0.0) -> bool:
        tilt2 = float((gravity_xy**2).sum(-1))
        return (tilt2 < self.max_tilt**2 and float(height_above_ground) >= self.min_height
                and float(base_speed) < self.max_speed and abs(float(ground_offset)) <= self.max_ground_offset)


STANDING = StandingTest()

__all__ = ["SUCCESS_THRESHOLD_M", "fall_flags", "StandingTest", "STANDING"]
