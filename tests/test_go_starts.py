"""Starts at t = 0 where the balance policy hands the robot over at the go (env.go_starts): the recorded
states, their placement at a task's stance, the env's resets and odometry from them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.go_starts import GoStates
from pipeline.envs.torch_math import yaw_angle
from pipeline.envs.tracking_env import TrackingEnv

from env_stand_clip import N, data, hold, quiet_cfg  # noqa: F401  (data: the module fixture)

REPO = Path(__file__).resolve().parent.parent
BALANCE = REPO / "models/pretrained/balance_heading_long/export"


def _turned(yaw: float) -> list[float]:
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


def _states(nq: int = 34, nv: int = 33, count: int = 1) -> dict:
    """`count` copies of one go state: 0.1 m ahead, 0.02 m high, turned 0.2 rad, moving 0.3 m/s ahead."""
    qpos, qvel = np.zeros((count, nq)), np.zeros((count, nv))
    qpos[:, 0:3] = [0.1, 0.0, 0.02]
    qpos[:, 3:7] = _turned(0.2)
    qpos[:, 7:] = 0.05
    qvel[:, 0] = 0.3
    qvel[:, 5] = 0.4  # yaw rate, in the base's own frame
    return {"qpos": qpos, "qvel": qvel}


def test_a_go_state_is_placed_at_the_stance_in_its_heading():
    go = GoStates(_states(), 34, 33, "cpu")
    stance, heading = torch.tensor([1.0, 2.0, 0.78]), torch.tensor(_turned(math.pi / 2), dtype=torch.float32)
    qpos, qvel = go.place(3, stance, heading)
    assert torch.allclose(qpos[:, 0:3], torch.tensor([1.0, 2.1, 0.80]).expand(3, 3), atol=1e-6)  # ahead is +y there
    assert torch.allclose(yaw_angle(qpos[:, 3:7]), torch.full((3,), math.pi / 2 + 0.2), atol=1e-6)
    assert torch.allclose(qvel[:, 0:3], torch.tensor([0.0, 0.3, 0.0]).expand(3, 3), atol=1e-6)
    assert torch.allclose(qvel[:, 5], torch.full((3,), 0.4)) and torch.allclose(qpos[:, 7:], torch.full((3, 27), 0.05))


def test_go_states_of_the_wrong_shape_are_refused():
    with pytest.raises(PipelineInputError, match="qpos"):
        GoStates(_states(nq=30), 34, 33, "cpu")
    with pytest.raises(PipelineInputError, match="qvel"):
        GoStates({"qpos": np.zeros((2, 34)), "qvel": np.zeros((3, 33))}, 34, 33, "cpu")


def test_env_starts_at_the_go_and_counts_odometry_from_there(data):
    states = _states(count=1)
    env = TrackingEnv(quiet_cfg(go_starts={"prob": 1.0}), data, num_envs=N, go_states=states)
    torch.manual_seed(0)
    env.reset()
    stance = data.motion.root_pos[0]  # the clip faces +x: the displacement adds as it is
    assert np.allclose(env.backend.qpos[:, 0:3].numpy(), stance + [0.1, 0.0, 0.02], atol=1e-5)
    assert np.allclose(env.backend.qpos[:, 7:].numpy(), 0.05, atol=1e-6)
    assert np.allclose(env.backend.qvel[:, 0].numpy(), 0.3, atol=1e-6)
    assert torch.allclose(env.odom_origin, env.backend.qpos[:, 0:3].to(env.odom_origin.dtype), atol=1e-6)
    assert torch.allclose(yaw_angle(env.odom_origin_quat), torch.full((N,), 0.2), atol=1e-5)
    assert torch.all(env.frame == 0)
    # the motors start holding where the balance policy left the joints, not the reference's
    assert torch.allclose(env.target_history[:, :], torch.full_like(env.target_history, 0.05), atol=1e-6)
    env.step(hold(env))  # and the episode runs from there


def test_go_starts_share_and_switch(data):
    states = _states(count=1)
    env = TrackingEnv(quiet_cfg(go_starts={"prob": 0.5}), data, num_envs=256, go_states=states)
    torch.manual_seed(0)
    env.reset()
    at_go = np.isclose(env.backend.qpos[:, 7].numpy(), 0.05)
    assert 0.35 < at_go.mean() < 0.65
    still = ~at_go  # the others start at the stance itself, where the odometry starts too
    assert np.allclose(env.backend.qpos[still, 0:3].numpy(), data.motion.root_pos[0], atol=1e-5)
    with pytest.raises(PipelineInputError, match="go_starts.prob"):
        TrackingEnv(quiet_cfg(go_starts={"prob": 0.5}), data, num_envs=2)  # no states given
    with pytest.raises(PipelineInputError, match="go_starts.prob"):
        quiet_cfg(go_starts={"prob": 1.5})


@pytest.mark.skipif(not (BALANCE / "policy.onnx").is_file(), reason="the committed balance policy")
def test_recorded_go_states_are_the_balance_policys_stand():
    from pipeline.balance.go_states import record_go_states

    torch.manual_seed(7)
    before = torch.get_rng_state()
    states = record_go_states(BALANCE, 3, stand_s=1.0)
    assert torch.equal(torch.get_rng_state(), before)  # the caller's random stream goes on untouched
    qpos, qvel = states["qpos"], states["qvel"]
    assert qpos.shape[1] == 34 and qvel.shape == (len(qpos), 33) and 1 <= len(qpos) <= 3
    # the first stand is nominal: near the stance, upright, and yet not the default pose at rest
    assert np.linalg.norm(qpos[0, 0:2]) < 0.1 and abs(qpos[0, 2]) < 0.05 and abs(qpos[0, 3]) > 0.99
    import json

    default = np.array(json.loads((BALANCE / "policy.json").read_text())["default_joint_pos"])
    assert np.abs(qpos[0, 7:] - default).max() > 0.02
    assert np.array_equal(record_go_states(BALANCE, 3, stand_s=1.0)["qpos"], qpos)  # seeded: the same stands
