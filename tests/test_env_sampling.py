"""Adaptive ψ sampling: failure-rate bookkeeping by hand, draws in proportion, the env's resets use it,
evaluation ignores it, bad config values are refused. Resume of its state: test_env_resume.py."""

from __future__ import annotations

import math

import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import EnvConfig, SamplingConfig
from pipeline.envs.sampling import SampleSampler
from pipeline.envs.tracking_env import TrackingEnv
from pipeline.evaluation.config import EvalConfig
from pipeline.evaluation.evaluate import evaluation_env_config
from test_env import data, quiet_cfg  # noqa: F401  (a 61-frame standing clip with 3 ψ samples)


def test_failure_rates_follow_finished_episodes_by_hand():
    sampler = SampleSampler(SamplingConfig(mode="adaptive", uniform_ratio=0.2, rate=0.05), num_samples=4)
    # two episodes of sample 0 (one failed), one successful episode of sample 1
    sampler.record(torch.tensor([0, 0, 1]), torch.tensor([True, False, False]))
    assert sampler.failure_rate.tolist() == pytest.approx([1.0 + 0.1 * (0.5 - 1.0), 1.0 - 0.05, 1.0, 1.0])
    sampler.record(torch.tensor([], dtype=torch.long), torch.tensor([], dtype=torch.bool))  # nothing ended
    assert sampler.failure_rate.tolist() == pytest.approx([0.95, 0.95, 1.0, 1.0])

    sampler.failure_rate = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    p = sampler.probabilities()
    assert p.tolist() == pytest.approx([0.05 + 0.8, 0.05, 0.05, 0.05])
    torch.manual_seed(0)
    counts = torch.bincount(sampler.draw(20000), minlength=4).double() / 20000
    assert counts[0] == pytest.approx(0.85, abs=0.015)
    assert counts[1:].tolist() == pytest.approx([0.05] * 3, abs=0.01)

    sampler.failure_rate.zero_()  # nothing fails any more: uniform again
    assert sampler.probabilities().tolist() == pytest.approx([0.25] * 4)
    assert SampleSampler(SamplingConfig(), 4).probabilities().tolist() == pytest.approx([0.25] * 4)


def test_env_resets_draw_from_the_sampler_and_record_falls(data):  # noqa: F811
    env = TrackingEnv(quiet_cfg(sampling={"mode": "adaptive", "uniform_ratio": 0.0, "rate": 0.5}), data, num_envs=4)
    env.sampler.failure_rate = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    env.reset()
    assert env.sample.tolist() == [2, 2, 2, 2]

    # world 0 topples: its episode (sample 2) ends as a failure and is recorded
    env.sampler.failure_rate = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    qpos = env.backend.qpos.clone()
    qpos[0, 3:7] = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    env.backend.set_state(torch.tensor([0]), qpos[:1], env.backend.qvel[:1].clone())
    _, _, term, _, _ = env.step(torch.zeros(4, env.action_dim))
    assert term.tolist() == [True, False, False, False]
    assert env.sampler.failure_rate.tolist() == pytest.approx([0.0, 1.0, 0.5])
    assert int(env.sample[0]) in (1, 2)  # the reset drew in proportion to the failure rates
    # uniform mode records nothing
    env = TrackingEnv(quiet_cfg(), data, num_envs=4)
    env.reset()
    env.backend.set_state(torch.tensor([0]), qpos[:1], env.backend.qvel[:1].clone())
    env.step(torch.zeros(4, env.action_dim))
    assert env.sampler.failure_rate.tolist() == [1.0, 1.0, 1.0]


def test_evaluation_scores_every_psi_alike():
    cfg = EnvConfig.from_dict({"sampling": {"mode": "adaptive"}})
    assert evaluation_env_config(cfg, EvalConfig()).sampling.mode == "uniform"
    assert cfg.sampling.mode == "adaptive"  # the training config is untouched


@pytest.mark.parametrize("raw, key", [({"mode": "hard_first"}, "sampling.mode"),
                                      ({"uniform_ratio": 1.5}, "sampling.uniform_ratio"),
                                      ({"rate": 0.0}, "sampling.rate")])
def test_bad_sampling_values_name_the_key(raw, key):
    with pytest.raises(PipelineInputError, match=key.replace(".", r"\.")):
        EnvConfig.from_dict({"sampling": raw})
