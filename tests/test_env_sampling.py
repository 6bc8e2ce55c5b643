"""ψ sampling: adaptive failure-rate bookkeeping and the curriculum's levels by hand, draws follow them,
the env's resets use the sampler and record only episodes that met the edit, evaluation ignores it,
bad config values are refused. Resume of its state: test_env_resume.py."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
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
    psi = np.array([0.2, 0.4, 0.6, 0.8])
    sampler = SampleSampler(SamplingConfig(mode="adaptive", uniform_ratio=0.2, rate=0.05), psi, 0.5, num_worlds=3)
    # two episodes of sample 0 (one failed), one successful episode of sample 1
    sampler.record(torch.tensor([0, 1, 2]), torch.tensor([0, 0, 1]), torch.tensor([True, False, False]))
    assert sampler.failure_rate.tolist() == pytest.approx([1.0 + 0.1 * (0.5 - 1.0), 1.0 - 0.05, 1.0, 1.0])
    nothing = torch.tensor([], dtype=torch.long)
    sampler.record(nothing, nothing, torch.tensor([], dtype=torch.bool))
    assert sampler.failure_rate.tolist() == pytest.approx([0.95, 0.95, 1.0, 1.0])

    sampler.failure_rate = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    p = sampler.probabilities()
    assert p.tolist() == pytest.approx([0.05 + 0.8, 0.05, 0.05, 0.05])
    torch.manual_seed(0)
    counts = torch.bincount(sampler.draw(torch.zeros(20000, dtype=torch.long)), minlength=4).double() / 20000
    assert counts[0] == pytest.approx(0.85, abs=0.015)
    assert counts[1:].tolist() == pytest.approx([0.05] * 3, abs=0.01)

    sampler.failure_rate.zero_()  # nothing fails any more: uniform again
    assert sampler.probabilities().tolist() == pytest.approx([0.25] * 4)
    assert SampleSampler(SamplingConfig(), psi, 0.5, 3).probabilities().tolist() == pytest.approx([0.25] * 4)


def test_curriculum_levels_by_hand():
    # |ψ − ψ_raw| = 0.1, 0, 0.4, 0.6, 0.9, 0.3 -> ranked samples 1, 0, 5, 2, 3, 4 -> levels {1, 0} {5, 2} {3, 4}
    psi = np.array([1.0, 1.1, 1.5, 0.5, 2.0, 0.8])
    sampler = SampleSampler(SamplingConfig(mode="curriculum", levels=3), psi, 1.1, num_worlds=4)
    assert sampler.level.tolist() == [0, 0, 0, 0] and sampler.mean_level() == 0.0
    torch.manual_seed(0)
    many = torch.zeros(3000, dtype=torch.long)  # 3000 draws for world 0
    assert set(sampler.draw(many).tolist()) == {0, 1}
    sampler.level[2] = 2
    assert set(sampler.draw(many + 2).tolist()) == {3, 4}
    assert torch.bincount(sampler.draw(many + 2), minlength=6)[3] == pytest.approx(1500, abs=120)

    # world 0 finishes (up), world 1 falls at the bottom (stays), world 3 climbs from 1 to the top
    sampler.level[3] = 1
    sampler.record(torch.tensor([0, 1, 3]), torch.tensor([1, 0, 5]), torch.tensor([False, True, False]))
    assert sampler.level.tolist() == [1, 0, 2, 2]
    sampler.record(torch.tensor([3]), torch.tensor([4]), torch.tensor([True]))  # a fall one level down
    assert sampler.level.tolist() == [1, 0, 2, 1]
    assert sampler.mean_level() == pytest.approx((1 + 0 + 2 + 1) / 4 / 2)
    # finishing the top level restarts a world at a random level: over many tries, all of them
    seen = set()
    for _ in range(60):
        sampler.level[2] = 2
        sampler.record(torch.tensor([2]), torch.tensor([3]), torch.tensor([False]))
        seen.add(int(sampler.level[2]))
    assert seen == {0, 1, 2}

    restored = SampleSampler(SamplingConfig(mode="curriculum", levels=3), psi, 1.1, num_worlds=4)
    restored.load_state_dict(sampler.state_dict())
    assert torch.equal(restored.level, sampler.level)
    with pytest.raises(PipelineInputError, match="sampler.level"):
        SampleSampler(SamplingConfig(mode="curriculum", levels=3), psi, 1.1, num_worlds=5).load_state_dict(sampler.state_dict())
    assert SampleSampler(SamplingConfig(mode="curriculum", levels=8), psi, 1.1, num_worlds=4).num_levels == 6


def test_only_episodes_that_met_the_edit_are_recorded(data):  # noqa: F811
    # the edit starts at the second keyframe (frame 25): an episode started there or later says nothing about ψ
    edited_late = dataclasses.replace(data, edited=np.array([False, True, False]))
    env = TrackingEnv(quiet_cfg(sampling={"mode": "curriculum", "levels": 3}), edited_late, num_envs=4)
    assert env.first_edit_frame == 25
    env.reset()
    env.sampler.level[:] = 1
    env.start_frame[1] = 25  # as if world 1 had started from a reference state at the edited keyframe
    qpos = env.backend.qpos.clone()
    toppled = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    qpos[:2, 3:7] = toppled
    env.backend.set_state(torch.tensor([0, 1]), qpos[:2], env.backend.qvel[:2].clone())
    _, _, term, _, _ = env.step(torch.zeros(4, env.action_dim))
    assert term.tolist() == [True, True, False, False]
    assert env.sampler.level.tolist() == [0, 1, 1, 1]  # world 0's fall counted, world 1's did not
    assert env.start_frame[:2].tolist() == [0, 0]  # both restarted at t = 0 (no RSI)


def test_env_resets_draw_from_the_sampler_and_record_falls(data):  # noqa: F811
    env = TrackingEnv(quiet_cfg(sampling={"mode": "adaptive", "uniform_ratio": 0.0, "rate": 0.5}), data, num_envs=4)
    env.sampler.failure_rate = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    env.reset()
    assert env.sample.tolist() == [2, 2, 2, 2]
    assert env.first_edit_frame == 10  # every keyframe edited: episodes from t = 0 meet the edit

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
    env = TrackingEnv(quiet_cfg(sampling={"mode": "uniform"}), data, num_envs=4)
    env.reset()
    env.backend.set_state(torch.tensor([0]), qpos[:1], env.backend.qvel[:1].clone())
    env.step(torch.zeros(4, env.action_dim))
    assert env.sampler.failure_rate.tolist() == [1.0, 1.0, 1.0]


def test_sweep_gives_every_sample_in_turn():
    sampler = SampleSampler(SamplingConfig(mode="sweep"), np.linspace(0.2, 2.0, 5), 1.1, num_worlds=3)
    first = sampler.draw(torch.arange(3))
    again = sampler.draw(torch.tensor([1]))  # world 1 ends first: its second episode
    rest = sampler.draw(torch.tensor([0, 2]))
    assert first.tolist() == [0, 1, 2] and again.tolist() == [4] and rest.tolist() == [3, 0]
    assert sampler.draw(torch.tensor([1])).tolist() == [2]  # (1 + 2·3) mod 5
    # 5 worlds × 4 episodes over 5 samples: each sample exactly 4 times, in any finishing order
    sampler = SampleSampler(SamplingConfig(mode="sweep"), np.linspace(0.2, 2.0, 5), 1.1, num_worlds=5)
    drawn = torch.cat([sampler.draw(torch.randperm(5)) for _ in range(4)])
    assert torch.bincount(drawn).tolist() == [4] * 5


def test_evaluation_scores_every_psi_alike():
    for mode in ("uniform", "adaptive", "curriculum"):
        cfg = EnvConfig.from_dict({"sampling": {"mode": mode}})
        assert evaluation_env_config(cfg, EvalConfig()).sampling.mode == "sweep"
        assert cfg.sampling.mode == mode  # the training config is untouched


@pytest.mark.parametrize("raw, key", [({"mode": "hard_first"}, "sampling.mode"),
                                      ({"mode": "curriculum", "levels": 1}, "sampling.levels"),
                                      ({"uniform_ratio": 1.5}, "sampling.uniform_ratio"),
                                      ({"rate": 0.0}, "sampling.rate")])
def test_bad_sampling_values_name_the_key(raw, key):
    with pytest.raises(PipelineInputError, match=key.replace(".", r"\.")):
        EnvConfig.from_dict({"sampling": raw})
