"""clip.lead_in_s: a task that starts at the stance at rest and moves into its window's first frame."""

import numpy as np
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.lead_in import with_lead_in
from pipeline.robot.g1 import load_robot_config


def _crouching_data():
    from test_export import _tracking_data

    data = _tracking_data(wave=0.3)  # every joint off the default pose at frame 0 already
    data.dense_offsets = np.random.default_rng(0).normal(size=(data.num_samples, data.motion.num_frames, 3))
    return data


def test_the_lead_in_starts_at_the_stance_at_rest_and_reaches_the_first_frame():
    data = _crouching_data()
    robot = load_robot_config()
    led = with_lead_in(data, 0.5)
    frames = 25
    m = led.motion
    assert m.num_frames == data.motion.num_frames + frames
    assert np.allclose(m.joint_pos[0], robot.default_joint_pos) and np.allclose(m.joint_pos[1], robot.default_joint_pos)
    assert np.allclose(m.joint_pos[frames:], data.motion.joint_pos) and np.allclose(m.body_pos[frames:], data.motion.body_pos)
    # at rest at its start, and arriving smoothly: the last lead-in frame is next to the window's first
    assert np.allclose(m.qvel()[0], 0.0, atol=1e-6)
    assert np.abs(m.joint_pos[frames - 1] - m.joint_pos[frames]).max() < 0.01
    # on the window's ground, under the window's start, facing its way
    feet = [robot.tracked_body_names.index(n) for n in ("left_ankle", "right_ankle")]
    assert m.body_pos[0, feet, 2].min() == pytest.approx(data.motion.body_pos[0, feet, 2].min(), abs=1e-6)
    assert np.allclose(m.root_pos[0, :2], data.motion.root_pos[0, :2])
    assert np.array_equal(led.keyframe_frames, np.asarray(data.keyframe_frames) + frames)
    assert np.array_equal(led.dense_offsets[:, :frames], np.repeat(data.dense_offsets[:, :1], frames, axis=1))
    assert with_lead_in(data, 0.0) is data


def test_a_negative_lead_in_names_the_key():
    from pipeline.keyframes.config import TaskConfig

    raw = {"input": "x.npz", "edit": {"mode": "x", "keyframes": ["landing"]},
           "psi": {"raw": 1.0, "easy": [[0.5, 1.5]], "hard": [[1.5, 2.0]]}, "clip": {"lead_in_s": -1.0}}
    with pytest.raises(PipelineInputError, match="clip.lead_in_s"):
        TaskConfig.from_dict("t", raw)
    raw["clip"] = {"lead_in_s": 0.5}
    assert TaskConfig.from_dict("t", raw).clip.lead_in_s == 0.5
