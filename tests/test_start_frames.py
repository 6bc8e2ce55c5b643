"""Reference-state start frames: uniform as before, or adaptive to where episodes that started there fail."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import EnvConfig, StartFrameSamplingConfig
from pipeline.envs.start_frames import StartFrameSampler, allowed_start_frames

FRAMES = torch.arange(4, 84)  # 80 start frames, frames 0-3 not in the table


def sampler(**kw) -> StartFrameSampler:
    return StartFrameSampler(StartFrameSamplingConfig(**kw), FRAMES, num_frames=100)


def test_uniform_draws_are_the_plain_draw_of_the_table():
    torch.manual_seed(3)
    got = sampler().draw(500)
    torch.manual_seed(3)
    assert torch.equal(got, FRAMES[torch.randint(FRAMES.numel(), (500,))])  # the same random stream as before


def test_adaptive_draws_follow_the_failure_rate_of_each_group():
    s = sampler(mode="adaptive", bins=4, uniform_share=0.2, rate_smoothing=1.0)
    starts = FRAMES[torch.arange(0, 80, 2)]  # 10 starts in each group of 20 frames
    failed = (starts >= 44) & (starts < 64)  # only the third group (frames 44-63) fails
    s.record(starts, failed)
    assert torch.allclose(s.failure_rate, torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=torch.float64))
    expected = torch.tensor([0.05, 0.05, 0.85, 0.05], dtype=torch.float64)  # 0.2 · 1/4 + 0.8 · rate / Σ rate
    assert torch.allclose(s.probabilities(), expected)
    torch.manual_seed(0)
    frames = s.draw(20000)
    assert bool(((frames >= 4) & (frames < 84)).all())
    share = ((frames >= 44) & (frames < 64)).double().mean()
    assert abs(float(share) - 0.85) < 0.01
    assert len(torch.unique(frames[(frames >= 44) & (frames < 64)])) == 20  # every frame of the group is drawn


def test_rates_are_running_means_and_ignore_episodes_from_t0():
    s = sampler(mode="adaptive", bins=2, rate_smoothing=0.5)
    s.record(torch.tensor([0, 0, 0]), torch.tensor([True, True, True]))  # t = 0 episodes: not charged
    assert torch.equal(s.failure_rate, torch.ones(2, dtype=torch.float64))
    s.record(torch.tensor([10, 12, 60]), torch.tensor([False, True, False]))
    assert torch.allclose(s.failure_rate, torch.tensor([0.5 + 0.5 * 0.5, 0.5], dtype=torch.float64))


def test_a_snapshot_of_another_group_count_is_refused():
    state = sampler(mode="adaptive", bins=4).state_dict()
    with pytest.raises(PipelineInputError, match="failure_rate"):
        sampler(mode="adaptive", bins=8).load_state_dict(state)


@pytest.mark.parametrize("key, value", [("mode", "worst"), ("bins", 0), ("uniform_share", 1.5), ("rate_smoothing", 0.0)])
def test_bad_settings_are_refused_by_name(key, value):
    with pytest.raises(PipelineInputError, match=f"rsi_sampling.{key}"):
        EnvConfig.from_dict({"rsi_sampling": {key: value}})


def test_stance_starts_skip_the_flight_and_the_last_frame():
    keyframes = np.array([0, 10, 20, 30, 39])
    labels = ["", "takeoff", "landing", "", ""]
    stance = allowed_start_frames("stance", keyframes, labels, num_frames=40)
    assert stance.tolist() == list(range(0, 11)) + list(range(20, 39))  # the takeoff and landing frames stay
    assert allowed_start_frames("keyframes", keyframes, labels, 40).tolist() == [0, 10, 20, 30]
    # a takeoff with no landing after it: the rest of the clip is in the air
    assert allowed_start_frames("stance", keyframes, ["", "", "", "takeoff_2", ""], 40).tolist() == list(range(0, 31))
    assert allowed_start_frames("stance", keyframes, None, 40).tolist() == list(range(39))
