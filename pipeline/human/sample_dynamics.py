"""The sample's centre-of-mass plans (pipeline/human/sample.py): the push-off and the landing as a linear inverted
pendulum about a zero-moment point held on the feet, so the authored jump asks no more of the ankles than a robot has."""

from __future__ import annotations

import numpy as np

GRAVITY = 9.81


def pendulum(height, times: np.ndarray, x0: float, v0: float, zmp: float, steps_per_frame: int = 20):
    """The centre of mass's horizontal path (at `times`) and its speed at times[-1] when its zero-moment
    point is held at `zmp`: x'' = (g + z'') / z (x - zmp), the inverted pendulum of the planned
    height z(t) = height(t). Semi-implicit Euler, `steps_per_frame` steps per frame."""
    dt = (times[1] - times[0]) / steps_per_frame
    fine = times[0] + dt * np.arange((len(times) - 1) * steps_per_frame + 1)
    stiffness = (GRAVITY + height(fine, 2)) / height(fine)
    x, v = x0, v0
    path = np.empty(len(fine))
    for i, k in enumerate(stiffness):
        path[i] = x
        if i + 1 < len(fine):
            v += k * (x - zmp) * dt
            x += v * dt
    return path[::steps_per_frame], v


def bisect(f, low: float, high: float, iterations: int = 60) -> float:
    """A root of f, decreasing on [low, high]: f(low) > 0 > f(high)."""
    for _ in range(iterations):
        mid = 0.5 * (low + high)
        if f(mid) > 0.0:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)


def balanced_landing(height, times, x_takeoff: float, x_rest: float, flight_time: float):
    """The centre of mass's horizontal path after touch-down (at times[0]) and the flight's speed vx.

    The zero-moment point is held at x_rest, where the final standing pose has its centre of mass
    over the landed feet, so the robot can do it without tipping. Of the touch-down points D behind
    x_rest (reached by a flight from x_takeoff with vx = (x_rest - D - x_takeoff) / T), too near ones
    overshoot x_rest and too far ones fall back: the one that comes to rest is found by bisection.
    """
    def flight_speed(distance):
        return (x_rest - distance - x_takeoff) / flight_time

    def overshoot(distance):
        return pendulum(height, times, x_rest - distance, flight_speed(distance), x_rest)[0].max() - x_rest

    distance = bisect(overshoot, 0.0, x_rest - x_takeoff)
    return pendulum(height, times, x_rest - distance, flight_speed(distance), x_rest)[0], flight_speed(distance)


def planned_push(height, times, x_start: float, v_start: float, zmp_range: tuple[float, float], land):
    """The centre of mass's horizontal path through the push-off (times[0] .. take-off at times[-1])
    and its take-off speed.

    The push starts from the crouch's own position and speed, and the zero-moment point is held at one
    place on the feet, so the ankles need not hold the body up on the toes (the pose-driven push the
    sample had before asked 2.2 times the G1's ankle torque). The place is the one whose take-off
    speed is what `land(x_takeoff)` (the flight and landing plan) needs from where the push ends.
    """
    def surplus(zmp):  # decreasing: a zero-moment point further forward pushes less
        path, speed = pendulum(height, times, x_start, v_start, zmp)
        return speed - land(path[-1])[1]

    low, high = zmp_range
    if not surplus(low) > 0.0 > surplus(high):
        raise ValueError(f"sample push-off: no zero-moment point in {zmp_range} gives the take-off speed "
                         "the landing needs")
    return pendulum(height, times, x_start, v_start, bisect(surplus, low, high))
