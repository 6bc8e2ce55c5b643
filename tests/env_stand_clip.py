"""The standing clip the TrackingEnv tests share: the G1's default pose held for 1.2 s with the left elbow
swinging, three keyframes moved forward by ψ, and the quiet configuration that tracks it to the end."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.envs.config import EnvConfig
from pipeline.keyframes.tracking_data import TrackingData
from pipeline.motion.motion import RobotKinematics

FRAMES = 61  # 1.2 s at 50 fps
KEYFRAMES = np.array([10, 25, 40])
N = 4


def stand_data() -> TrackingData:
    kin = RobotKinematics()
    rc = kin.config
    t = np.arange(FRAMES) / 50.0
    joints = np.tile(rc.default_joint_pos, (FRAMES, 1))
    joints[:, rc.joint_names.index("left_elbow_joint")] += 0.3 * np.sin(2 * np.pi * t)
    root = np.tile([0.0, 0.0, rc.default_root_height], (FRAMES, 1))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (FRAMES, 1))
    motion = kin.motion(50.0, root, quat, joints, name="stand")
    psi = np.array([0.0, 0.05, 0.1])
    offsets = np.zeros((3, len(KEYFRAMES), 3))
    offsets[:, :, 0] = psi[:, None]  # keyframe targets moved forward by ψ
    return TrackingData(task="stand", motion=motion, keyframe_frames=KEYFRAMES, keyframe_labels=("", "apex", ""),
                        sparse_scale=np.array([1.0, 50.0, 1.0]), edited=np.ones(3, bool), psi=psi,
                        keyframe_offsets=offsets)


@pytest.fixture(scope="module")
def data() -> TrackingData:
    """The standing clip as a module fixture: `from env_stand_clip import data` in a test module."""
    return stand_data()


def quiet_cfg(**extra) -> EnvConfig:
    """No randomisation, no RSI, no odometry noise: a standing robot tracks the clip to the end. ψ drawn
    uniformly, so the worlds track different samples from the first reset (a curriculum starts them all
    at the sample nearest ψ_raw)."""
    raw = {"randomization": {"enabled": False}, "rsi_prob": 0.0, "observations": {"odometry_noise_std": 0.0},
           "sampling": {"mode": "uniform"}}
    for key, value in extra.items():
        raw[key] = {**raw.get(key, {}), **value} if isinstance(value, dict) else value
    return EnvConfig.from_dict(raw)


def hold(env) -> torch.Tensor:
    return torch.zeros(env.num_envs, env.action_dim)
