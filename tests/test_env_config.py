"""EnvConfig parsing and the pure reward terms against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs import rewards as R
from pipeline.envs.config import EnvConfig
from pipeline.envs.randomization import restitution_to_dampratio
from pipeline.envs.torch_math import projected_gravity, quat_mul, quat_rotate, quat_rotate_inverse, yaw_quat


def test_defaults_are_the_papers():
    cfg = EnvConfig.from_dict({})
    w = cfg.rewards.weights
    assert (w.global_body_pos, w.global_body_rot, w.global_feet_pos, w.termination) == (10, 5, 10, -200)
    assert (w.local_body_pos, w.local_body_rot, w.local_joint_pos) == (0.75, 0.5, 0.75)
    assert (w.joint_acc, w.joint_vel, w.action_rate, w.smoothness, w.torques) == (-2.5e-7, -5e-4, -0.5, -0.01, -1e-6)
    assert (w.joint_pos_limits, w.joint_vel_limits, w.feet_orientation) == (-10, -5, -0.05)
    assert cfg.observations.history == 5 and cfg.observations.odometry_rate_hz == 10
    c = cfg.terminations.keyframe_error
    assert (c.start, c.min, c.max) == (1.5, 0.6, 2.0)
    r = cfg.randomization
    assert (r.trunk_mass_add.low, r.trunk_mass_add.high) == (-2, 5)
    assert (r.control_delay_ms.low, r.control_delay_ms.high) == (0, 100)
    assert EnvConfig.from_dict(cfg.to_dict()) == cfg  # round trip


def test_partial_override_and_errors_name_the_key():
    cfg = EnvConfig.from_dict({"rewards": {"weights": {"torques": -2e-6}}, "randomization": {"friction": {"enabled": False}}})
    assert cfg.rewards.weights.torques == -2e-6 and cfg.rewards.weights.joint_vel == -5e-4
    assert not cfg.randomization.friction.enabled and cfg.randomization.friction.high == 1.1
    cases = [
        ({"rewards": {"weights": {"torque": 1}}}, "env.rewards.weights.torque"),
        ({"observations": {"history": 2.5}}, "env.observations.history"),
        ({"rsi_prob": 1.5}, "rsi_prob"),
        ({"action_offset": "pose"}, "action_offset"),
        ({"variant": {"tracking": "both"}}, "variant.tracking"),
        ({"randomization": {"friction": {"low": 2.0, "high": 1.0}}}, "randomization.friction"),
        ({"randomization": {"push": {"enabled": "yes"}}}, "env.randomization.push.enabled"),
        ({"terminations": {"keyframe_error": {"start": 3.0}}}, "keyframe_error"),
        ({"terminations": {"keyframe_error": {"measure": "median"}}}, "keyframe_error.measure"),
        ({"rewards": {"sigma2": {"feet_pos": 0}}}, "sigma2.feet_pos"),
        ({"rewards": "x"}, "env.rewards"),
    ]
    for raw, key in cases:
        with pytest.raises(PipelineInputError) as err:
            EnvConfig.from_dict(raw)
        assert key in str(err.value), (raw, str(err.value))


def test_kernels_hand_values():
    pos = torch.zeros(1, 2, 3)
    target = torch.tensor([[[0.1, 0.0, 0.0], [0.0, 0.2, 0.0]]])
    inv = torch.tensor([1 / 0.03, 1 / 0.1])
    expected = math.exp(-(0.01 / 0.03 + 0.04 / 0.1) / 2)
    assert R.position_kernel(pos, target, inv).item() == pytest.approx(expected, rel=1e-6)
    q = torch.tensor([[[1.0, 0, 0, 0], [1.0, 0, 0, 0]]])
    half = math.pi / 4  # 90° about z for the second body
    t = torch.tensor([[[1.0, 0, 0, 0], [math.cos(half), 0, 0, math.sin(half)]]])
    assert R.rotation_kernel(q, t, 1.0).item() == pytest.approx(math.exp(-(math.pi / 2) ** 2 / 2), rel=1e-5)
    j = torch.zeros(1, 4)
    assert R.joint_kernel(j, torch.tensor([[0.1, 0.2, 0.0, 0.0]]), 1.0).item() == pytest.approx(math.exp(-0.05 / 4))


def test_penalty_terms_hand_values():
    a, p, p2 = torch.tensor([[1.0, 2.0]]), torch.tensor([[0.5, 1.0]]), torch.tensor([[0.0, 1.0]])
    assert R.sum_sq(a - p).item() == pytest.approx(0.25 + 1.0)
    assert R.smoothness(a, p, p2).item() == pytest.approx(0.0**2 + 1.0**2)
    assert R.over_limit(torch.tensor([[3.0, -5.0, 1.0]]), torch.tensor([2.0, 4.0, 2.0])).item() == pytest.approx(2.0)
    lo, hi = R.soft_range(np.array([-1.0]), np.array([3.0]), 0.5)
    assert (lo[0], hi[0]) == (0.0, 2.0)
    out = R.outside_range(torch.tensor([[-0.5, 2.5, 1.0]]), torch.tensor([0.0, 0.0, 0.0]), torch.tensor([2.0, 2.0, 2.0]))
    assert out.item() == pytest.approx(1.0)
    # a foot rolled by 0.3 rad in contact: |g_xy|² = sin²(0.3); the other foot flat
    roll = torch.tensor([math.cos(0.15), math.sin(0.15), 0.0, 0.0])
    feet = torch.stack([roll, torch.tensor([1.0, 0, 0, 0])])[None]
    assert R.feet_orientation(feet, torch.tensor([[1.0, 1.0]])).item() == pytest.approx(math.sin(0.3) ** 2, rel=1e-5)
    assert R.feet_orientation(feet, torch.tensor([[0.0, 1.0]])).item() == 0.0


def test_quaternion_helpers():
    torch.manual_seed(0)
    q = torch.nn.functional.normalize(torch.randn(16, 4), dim=-1)
    v = torch.randn(16, 3)
    assert torch.allclose(quat_rotate_inverse(q, quat_rotate(q, v)), v, atol=1e-5)
    assert torch.allclose(projected_gravity(q), quat_rotate_inverse(q, torch.tensor([0.0, 0, -1]).expand(16, 3)), atol=1e-5)
    yaw = yaw_quat(q)
    fwd = quat_rotate(q, torch.tensor([1.0, 0, 0]).expand(16, 3))
    fwd_yaw = quat_rotate(yaw, torch.tensor([1.0, 0, 0]).expand(16, 3))
    heading = torch.atan2(fwd[:, 1], fwd[:, 0])
    assert torch.allclose(torch.atan2(fwd_yaw[:, 1], fwd_yaw[:, 0]), heading, atol=1e-4)
    assert torch.allclose(quat_mul(q, torch.tensor([1.0, 0, 0, 0]).expand(16, 4)), q)


def test_restitution_mapping():
    assert restitution_to_dampratio(np.array([0.0]))[0] == pytest.approx(1.0)
    zeta = restitution_to_dampratio(np.array([0.1]))[0]
    assert math.exp(-zeta * math.pi / math.sqrt(1 - zeta**2)) == pytest.approx(0.1, rel=1e-6)
