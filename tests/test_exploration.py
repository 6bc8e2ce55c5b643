"""Time-correlated exploration noise (`ppo.noise_correlation`, pipeline/rl/exploration.py)."""

from __future__ import annotations

import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.rl.config import TrainConfig
from pipeline.rl.exploration import CorrelatedNoise
from pipeline.rl.networks import Stage1Policy
from pipeline.rl.stage2 import Stage2Policy


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_each_step_is_standard_normal_and_successive_steps_correlate_by_rho(rho):
    torch.manual_seed(0)
    noise = CorrelatedNoise(num_worlds=4000, dim=3, correlation=rho, device="cpu")
    draws = torch.stack([noise.next() for _ in range(40)])  # (T, N, D)
    late = draws[20:]
    assert late.mean().abs() < 0.02
    assert (late.std() - 1.0).abs() < 0.02
    lag1 = (draws[1:] * draws[:-1]).mean() / (draws[:-1] ** 2).mean()
    lag5 = (draws[5:] * draws[:-5]).mean() / (draws[:-5] ** 2).mean()
    assert abs(float(lag1) - rho) < 0.02
    assert abs(float(lag5) - rho**5) < 0.02


def test_restart_redraws_only_the_worlds_whose_episode_ended():
    torch.manual_seed(0)
    noise = CorrelatedNoise(num_worlds=2000, dim=2, correlation=0.95, device="cpu")
    before = noise.next()
    ended = torch.arange(2000) % 2 == 0
    noise.restart(ended)
    after = noise.next()
    kept = (after[~ended] * before[~ended]).mean() / (before[~ended] ** 2).mean()
    fresh = (after[ended] * before[ended]).mean() / (before[ended] ** 2).mean()
    assert abs(float(kept) - 0.95) < 0.02
    assert abs(float(fresh)) < 0.05
    assert (after[ended].std() - 1.0).abs() < 0.05


def test_the_state_round_trips():
    torch.manual_seed(0)
    noise = CorrelatedNoise(8, 2, 0.8, "cpu")
    noise.next()
    copy = CorrelatedNoise(8, 2, 0.8, "cpu")
    copy.load_state_dict(noise.state_dict())
    torch.manual_seed(1)
    a = noise.next(), noise.next()
    torch.manual_seed(1)
    b = copy.next(), copy.next()
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_policies_act_with_the_given_noise_and_score_it_under_their_own_gaussian():
    torch.manual_seed(0)
    base = Stage1Policy(5, 3, [16], init_log_std=-0.7)
    obs, eps = torch.randn(7, 5), torch.randn(7, 3)
    raw, log_prob = base.sample(obs, eps)
    dist = base.distribution(obs)
    assert torch.allclose(raw, dist.mean + dist.stddev * eps)
    assert torch.allclose(log_prob, dist.log_prob(raw).sum(-1))

    stage2 = Stage2Policy(base, [16], init_log_std=-1.0)
    eps = torch.randn(7, stage2.raw_dim)
    raw, log_prob = stage2.sample(obs, eps)
    std = stage2.log_std.exp()
    phase_mean, _ = stage2._means(obs, None)
    _, track_mean = stage2._means(obs, raw[:, 0])
    assert torch.allclose(raw[:, 0], phase_mean + std[0] * eps[:, 0])
    assert torch.allclose(raw[:, 1:], track_mean + std[1:] * eps[:, 1:])
    assert torch.allclose(log_prob, stage2.log_prob_entropy(obs, raw)[0])


@pytest.mark.parametrize("bad", [-0.1, 1.0])
def test_a_correlation_outside_zero_to_one_is_refused_naming_the_key(bad):
    with pytest.raises(PipelineInputError, match="noise_correlation"):
        TrainConfig.from_dict({"ppo": {"noise_correlation": bad}})
