"""Batched quaternion maths in torch, scalar-first (w, x, y, z) like MuJoCo; broadcasts over leading dims.

Written with plain elementwise ops (no cross/stack chains) to keep the per-step op count low on CPU.
"""

from __future__ import annotations

import torch


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_from_rotvec(rotvec: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (..., 4) of the rotation vector (..., 3): its direction the axis, its norm the angle."""
    angle = rotvec.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(θ/2)/θ → 1/2 as θ → 0: the small-angle form keeps a zero vector exact
    scale = torch.where(angle > 1e-8, torch.sin(half) / angle.clamp(min=1e-8), torch.full_like(angle, 0.5))
    return torch.cat([torch.cos(half), rotvec * scale], dim=-1)


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotates v (..., 3) by unit q (..., 4): v + 2w (u×v) + 2 u×(u×v)."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v + w * t + torch.linalg.cross(u, t, dim=-1)


def quat_rotate_inverse(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v - w * t + torch.linalg.cross(u, t, dim=-1)


def quat_angle_sq(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared rotation angle between unit quaternions a and b (...,): (2 acos |<a, b>|)²."""
    dot = (a * b).sum(-1).abs().clamp(max=1.0)
    return (2.0 * torch.acos(dot)) ** 2


def projected_gravity(q: torch.Tensor) -> torch.Tensor:
    """World gravity direction (0, 0, −1) in the frame of q, without a general rotation."""
    w, x, y, z = q.unbind(-1)
    return torch.stack((2.0 * (w * y - x * z), -2.0 * (y * z + w * x), -(1.0 - 2.0 * (x * x + y * y))), dim=-1)


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Angles to (−π, π]."""
    return torch.remainder(a + torch.pi, 2.0 * torch.pi) - torch.pi


def yaw_angle(q: torch.Tensor) -> torch.Tensor:
    """The heading of q (rad, about world z, in (−π, π])."""
    w, x, y, z = q.unbind(-1)
    return torch.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_quat(q: torch.Tensor) -> torch.Tensor:
    """The heading (rotation about world z) part of q."""
    yaw = yaw_angle(q)
    zero = torch.zeros_like(yaw)
    return torch.stack((torch.cos(0.5 * yaw), zero, zero, torch.sin(0.5 * yaw)), dim=-1)
