"""Reward terms of the tracking environment as pure batched functions (paper, Table "Reward functions").

Each returns the unweighted term (N,); the environment multiplies by the weights of `RewardWeights`
and sums them into the sparse and dense groups. Tracking terms are exponential kernels
exp(−mean_b(err_b² / σ_b²)): with one σ for every item this is exp(−mse/σ²); positions give the
upper and lower body their own σ² by weighting each body's squared error by its own 1/σ².
"""

from __future__ import annotations

import torch

from pipeline.envs.torch_math import projected_gravity, quat_angle_sq


def position_kernel(pos: torch.Tensor, target: torch.Tensor, inv_sigma2: torch.Tensor) -> torch.Tensor:
    """pos, target (N, B, 3); inv_sigma2 (B,) per-body 1/σ²."""
    err2 = ((pos - target) ** 2).sum(-1)
    return torch.exp(-(err2 * inv_sigma2).mean(-1))


def rotation_kernel(quat: torch.Tensor, target: torch.Tensor, sigma2: float) -> torch.Tensor:
    """quat, target (N, B, 4) unit wxyz; error = rotation angle."""
    return torch.exp(-quat_angle_sq(quat, target).mean(-1) / sigma2)


def joint_kernel(joint_pos: torch.Tensor, target: torch.Tensor, sigma2: float) -> torch.Tensor:
    return torch.exp(-((joint_pos - target) ** 2).mean(-1) / sigma2)


def vector_kernel(value: torch.Tensor, target: torch.Tensor, sigma2: float) -> torch.Tensor:
    """value, target (N, D): exp(−|value − target|² / σ²), the whole vector's error at once."""
    return torch.exp(-((value - target) ** 2).sum(-1) / sigma2)


def feet_orientation(feet_quat: torch.Tensor, contact: torch.Tensor) -> torch.Tensor:
    """Σ over feet in contact of |gravity_xy in the foot frame|²: zero when the soles are flat."""
    g = projected_gravity(feet_quat)
    return ((g[..., 0] ** 2 + g[..., 1] ** 2) * contact).sum(-1)


def sum_sq(x: torch.Tensor) -> torch.Tensor:
    return (x * x).sum(-1)


def smoothness(action: torch.Tensor, prev: torch.Tensor, prev2: torch.Tensor) -> torch.Tensor:
    """Second difference of the actions."""
    return sum_sq(action - 2.0 * prev + prev2)


def over_limit(value: torch.Tensor, limit: torch.Tensor) -> torch.Tensor:
    """Σ max(|value| − limit, 0): torque and joint-velocity limits (limit already softened)."""
    return torch.relu(value.abs() - limit).sum(-1)


def outside_range(value: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """Σ distance outside [low, high]: joint position limits."""
    return (torch.relu(low - value) + torch.relu(value - high)).sum(-1)


def soft_range(low, high, fraction: float):
    """[low, high] shrunk about its centre to `fraction` of its width."""
    mid, half = 0.5 * (low + high), 0.5 * (high - low) * fraction
    return mid - half, mid + half
