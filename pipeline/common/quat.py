"""Quaternion maths on numpy arrays, scalar-first (w, x, y, z) as MuJoCo stores them.

Every function broadcasts over leading dimensions.
"""

from __future__ import annotations

import numpy as np


def normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotates vectors v (..., 3) by unit quaternions q (..., 4)."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def inverse_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return rotate(conjugate(q), v)


def from_axis_angle(rotvec: np.ndarray) -> np.ndarray:
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(x/2)/x -> 1/2 as x -> 0; the series keeps small angles exact.
    small = angle < 1e-8
    scale = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), rotvec * scale], axis=-1)


def to_axis_angle(q: np.ndarray) -> np.ndarray:
    q = normalize(q)
    q = np.where(q[..., :1] < 0.0, -q, q)  # shortest rotation
    vec = q[..., 1:]
    sin_half = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., :1])
    small = sin_half < 1e-8
    scale = np.where(small, 2.0, angle / np.where(small, 1.0, sin_half))
    return vec * scale


def to_matrix(q: np.ndarray) -> np.ndarray:
    q = normalize(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    m = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def from_matrix(m: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) to unit quaternions with w >= 0 (Shepperd's method)."""
    m = np.asarray(m, dtype=np.float64)
    r = m.reshape(-1, 3, 3)
    diag = np.stack([r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=-1)
    trace = diag.sum(-1)
    # Candidate quaternions, one per largest component; pick the best conditioned per row.
    cands = np.stack(
        [
            np.stack([1 + trace, r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1),
            np.stack([r[:, 2, 1] - r[:, 1, 2], 1 + 2 * diag[:, 0] - trace, r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0]], -1),
            np.stack([r[:, 0, 2] - r[:, 2, 0], r[:, 0, 1] + r[:, 1, 0], 1 + 2 * diag[:, 1] - trace, r[:, 1, 2] + r[:, 2, 1]], -1),
            np.stack([r[:, 1, 0] - r[:, 0, 1], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1], 1 + 2 * diag[:, 2] - trace], -1),
        ],
        axis=1,
    )
    best = np.argmax(np.concatenate([trace[:, None], diag], axis=-1), axis=-1)
    out = normalize(cands[np.arange(r.shape[0]), best])
    out = np.where(out[:, :1] < 0, -out, out)
    return out.reshape(m.shape[:-2] + (4,))


def yaw(q: np.ndarray) -> np.ndarray:
    """Heading angle about world z."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def from_yaw(angle: np.ndarray) -> np.ndarray:
    angle = np.asarray(angle, dtype=np.float64)
    zeros = np.zeros_like(angle)
    return np.stack([np.cos(angle / 2), zeros, zeros, np.sin(angle / 2)], axis=-1)


def make_continuous(q: np.ndarray) -> np.ndarray:
    """Flips signs along axis 0 so consecutive quaternions lie in the same hemisphere."""
    q = np.array(q, dtype=np.float64, copy=True)
    for t in range(1, q.shape[0]):
        flip = np.sum(q[t] * q[t - 1], axis=-1) < 0.0
        q[t][flip] *= -1.0
    return q


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    alpha = np.asarray(alpha, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.abs(dot).clip(-1.0, 1.0)
    theta = np.arccos(dot)
    sin_theta = np.sin(theta)
    near = sin_theta < 1e-6
    w0 = np.where(near, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / np.where(near, 1.0, sin_theta))
    w1 = np.where(near, alpha, np.sin(alpha * theta) / np.where(near, 1.0, sin_theta))
    return normalize(w0 * q0 + w1 * q1)


def angular_velocity(q: np.ndarray, dt: float, frame: str = "world") -> np.ndarray:
    """Angular velocity (T, ..., 3) of a quaternion track (T, ..., 4) by central differences.

    `frame="world"` gives it in the world frame (MuJoCo's free-joint qvel uses the body frame:
    pass `frame="body"`). End points use one-sided differences.
    """
    q = make_continuous(q)
    if q.shape[0] < 2:
        return np.zeros(q.shape[:-1] + (3,))
    nxt = np.concatenate([q[1:], q[-1:]], axis=0)
    prv = np.concatenate([q[:1], q[:-1]], axis=0)
    span = np.full(q.shape[0], 2.0 * dt)
    span[0] = span[-1] = dt
    if frame == "world":
        delta = multiply(nxt, conjugate(prv))
    elif frame == "body":
        delta = multiply(conjugate(prv), nxt)
    else:
        raise ValueError(f"frame must be 'world' or 'body', got {frame!r}")
    return to_axis_angle(delta) / span.reshape((-1,) + (1,) * (q.ndim - 1))
