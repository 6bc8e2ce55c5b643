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
from env_stand_clip import FRAMES, data, quiet_cfg  # noqa: F401  (a 61-frame standing clip with 3 ψ samples)


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


def test_curriculum_level_success_rates_by_hand():
    psi = np.array([1.0, 1.1, 1.5, 0.5, 2.0, 0.8])  # levels {1, 0} {5, 2} {3, 4}, as above
    sampler = SampleSampler(SamplingConfig(mode="curriculum", levels=3, level_rate=0.1), psi, 1.1, num_worlds=4)
    assert sampler.level_success.tolist() == [0.0, 0.0, 0.0]
    sampler.level[:] = torch.tensor([0, 0, 1, 2])
    # first episodes are averaged plainly: level 0 two episodes, one success; level 1 a fall; level 2 a success
    sampler.record(torch.tensor([0, 1, 2, 3]), torch.tensor([0, 1, 5, 3]), torch.tensor([False, True, True, False]))
    assert sampler.level_success.tolist() == pytest.approx([0.5, 0.0, 1.0])
    assert sampler.level_episodes.tolist() == [2, 1, 1]
    # level 0's third to tenth episodes: a mean over all ten (1/level_rate), successes 1 + 8
    for _ in range(2):
        sampler.level[:] = 0  # successes move the worlds up: put them back
        sampler.record(torch.arange(4), torch.zeros(4, dtype=torch.long), torch.zeros(4, dtype=torch.bool))
    assert sampler.level_success[0] == pytest.approx(9 / 10)
    # after that an EMA of step 0.1 per episode: a fall moves 0.9 to 0.9 - 0.1 * 0.9
    sampler.level[:] = 0
    sampler.record(torch.tensor([0]), torch.tensor([0]), torch.tensor([True]))
    assert sampler.level_success[0] == pytest.approx(0.81)
    assert sampler.level_success[1:].tolist() == pytest.approx([0.0, 1.0])
    restored = SampleSampler(SamplingConfig(mode="curriculum", levels=3), psi, 1.1, num_worlds=4)
    restored.load_state_dict(sampler.state_dict())
    assert torch.equal(restored.level_success, sampler.level_success)
    assert torch.equal(restored.level_episodes, sampler.level_episodes)


def test_split_sides_walk_each_side_of_the_clip_apart():
    # shorter side (ψ < 1.1): |Δ| 0.1, 0.6, 0.3 for samples 0, 3, 5 -> levels {0, 5} {3}
    # farther side: |Δ| 0, 0.4, 0.9 for samples 1, 2, 4 -> levels {1, 2} {4}; rows 0-1 short, 2-3 far
    psi = np.array([1.0, 1.1, 1.5, 0.5, 2.0, 0.8])
    cfg = SamplingConfig(mode="curriculum", levels=2, split_sides=True)
    sampler = SampleSampler(cfg, psi, 1.1, num_worlds=6)
    assert sampler.level_side == [0, 0, 1, 1]
    assert [sorted(sampler.level_table[l, :sampler.level_size[l]].tolist()) for l in range(4)] == [[0, 5], [3], [1, 2], [4]]
    assert sampler.level.tolist() == [0, 0, 0, 2, 2, 2]  # three samples a side: three worlds a side
    torch.manual_seed(0)
    assert set(sampler.draw(torch.full((500,), 3)).tolist()) == {1, 2}

    # successes climb within the side, a fall at a side's bottom stays there
    sampler.record(torch.tensor([0, 1, 3, 4]), torch.tensor([0, 5, 1, 2]), torch.tensor([False, True, False, True]))
    assert sampler.level.tolist() == [1, 0, 0, 3, 2, 2]
    assert set(sampler.draw(torch.full((500,), 3)).tolist()) == {4}
    assert sampler.mean_level() == pytest.approx(2 / 6)
    sampler.record(torch.tensor([3]), torch.tensor([4]), torch.tensor([True]))
    assert sampler.level.tolist() == [1, 0, 0, 2, 2, 2]  # down to the far side's bottom, not below it
    # finishing a side's top level restarts the world on its own side
    seen_short, seen_far = set(), set()
    for _ in range(60):
        sampler.level[0], sampler.level[3] = 1, 3
        sampler.record(torch.tensor([0, 3]), torch.tensor([3, 4]), torch.tensor([False, False]))
        seen_short.add(int(sampler.level[0]))
        seen_far.add(int(sampler.level[3]))
    assert seen_short == {0, 1} and seen_far == {2, 3}
    # `relative` compares a level with its own side's bottom
    rel = SampleSampler(dataclasses.replace(cfg, demotion="relative", level_rate=1e-6), psi, 1.1, num_worlds=6)
    rel.level_success = torch.tensor([0.9, 0.8, 0.3, 0.25], dtype=torch.float64)
    rel.level_episodes[:] = 1e9
    rel.level[:] = torch.tensor([1, 1, 1, 3, 3, 3])
    rel.record(torch.tensor([0, 3]), torch.tensor([3, 4]), torch.tensor([True, True]))
    assert rel.level.tolist() == [1, 1, 1, 3, 3, 3]  # 0.8 > 0.8 * 0.9, 0.25 > 0.8 * 0.3 (not 0.9)
    # a range on one side of the clip has one side's levels, the pooled walk's
    one_sided = SampleSampler(cfg, np.array([1.1, 1.3, 1.6, 2.0]), 1.1, num_worlds=3)
    assert one_sided.level_side == [0, 0] and one_sided.level.tolist() == [0, 0, 0]
    assert one_sided.top_level.tolist() == [1, 1, 1]


def test_relative_demotion_ignores_falls_the_bottom_level_has_too():
    psi = np.array([1.0, 1.1, 1.5, 0.5, 2.0, 0.8])
    cfg = SamplingConfig(mode="curriculum", levels=3, demotion="relative", relative_ratio=0.8, level_rate=1e-6)
    sampler = SampleSampler(cfg, psi, 1.1, num_worlds=3)
    # the bottom succeeds 40 % of the time, level 1 35 % (within 0.8 of it), level 2 20 % (below)
    sampler.level_success = torch.tensor([0.4, 0.35, 0.2], dtype=torch.float64)
    sampler.level_episodes[:] = 1e9  # long measured: these episodes hardly move the rates
    sampler.level[:] = torch.tensor([0, 1, 2])
    sampler.record(torch.arange(3), torch.tensor([0, 2, 3]), torch.tensor([True, True, True]))
    assert sampler.level.tolist() == [0, 1, 1]  # only the fall at the measurably harder level 2 counts
    sampler.record(torch.tensor([1]), torch.tensor([2]), torch.tensor([False]))
    assert sampler.level.tolist() == [0, 2, 1]  # a success still climbs
    # "every_fall" (the default) sends every failing world down
    plain = SampleSampler(dataclasses.replace(cfg, demotion="every_fall"), psi, 1.1, num_worlds=3)
    plain.level_success = sampler.level_success.clone()
    plain.level[:] = torch.tensor([0, 1, 2])
    plain.record(torch.arange(3), torch.tensor([0, 2, 3]), torch.tensor([True, True, True]))
    assert plain.level.tolist() == [0, 0, 1]
    # before the bottom level has a success, only levels that never succeeded count a fall
    fresh = SampleSampler(cfg, psi, 1.1, num_worlds=2)
    fresh.level[:] = torch.tensor([1, 2])
    fresh.level_success = torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64)
    fresh.level_episodes[:] = 1e9
    fresh.record(torch.arange(2), torch.tensor([2, 3]), torch.tensor([True, True]))
    assert fresh.level.tolist() == [0, 2]


def test_relative_demotion_lets_worlds_climb_past_shared_falls():
    """A simulated policy that fails 60 % of its episodes at every level for reasons unrelated to ψ (the
    randomisation) and cannot do the top two levels at all: "every_fall" keeps the worlds near the bottom,
    "relative" brings them to the frontier."""
    psi = np.linspace(0.2, 2.0, 64)
    levels = 8

    def run(demotion: str) -> float:
        torch.manual_seed(0)
        sampler = SampleSampler(SamplingConfig(mode="curriculum", levels=levels, demotion=demotion), psi, 1.1, 256)
        for _ in range(300):
            worlds = torch.arange(256)
            level = sampler.level.clone()
            failed = (torch.rand(256) < 0.6) | (level >= levels - 2)
            sampler.record(worlds, sampler.draw(worlds), failed)
        return float(sampler.level.double().mean())

    every_fall, relative = run("every_fall"), run("relative")
    assert every_fall < 2.0  # a walk 40 % up and 60 % down stays near the bottom (a mean level ~1.5 of 7)
    assert relative > 3.0  # most worlds reach the levels they cannot do yet, or rehearse after graduating


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


def test_uniform_share_rehearses_every_level_without_moving_the_walk():
    psi = np.array([1.0, 1.1, 1.5, 0.5, 2.0, 0.8])  # levels {1, 0} {5, 2} {3, 4}
    sampler = SampleSampler(SamplingConfig(mode="curriculum", levels=3, uniform_share=0.25), psi, 1.1, num_worlds=4000)
    torch.manual_seed(0)
    drawn = sampler.draw(torch.arange(4000))  # every world at the bottom level {0, 1}
    away = ~torch.isin(drawn, torch.tensor([0, 1]))
    assert sampler.rehearsing.double().mean() == pytest.approx(0.25, abs=0.02)
    assert bool(sampler.rehearsing[away].all())  # only uniform draws leave the world's level
    assert away.double().mean() == pytest.approx(0.25 * 4 / 6, abs=0.02)
    # their outcomes count for the level of the sample drawn, but the worlds stay where they are
    rehearsed = torch.nonzero(sampler.rehearsing & (drawn == 4)).squeeze(-1)[:3]
    sampler.record(rehearsed, drawn[rehearsed], torch.tensor([False, False, True]))
    assert sampler.level_success.tolist() == pytest.approx([0.0, 0.0, 2 / 3])
    assert sampler.level[rehearsed].tolist() == [0, 0, 0]
    walked = torch.nonzero(~sampler.rehearsing).squeeze(-1)[:2]
    sampler.record(walked, drawn[walked], torch.tensor([False, True]))
    assert sampler.level[walked].tolist() == [1, 0]
    restored = SampleSampler(SamplingConfig(mode="curriculum", levels=3, uniform_share=0.25), psi, 1.1, num_worlds=4000)
    restored.load_state_dict(sampler.state_dict())
    assert torch.equal(restored.rehearsing, sampler.rehearsing)


def test_success_test_judges_episodes_as_the_evaluation_does(data):  # noqa: F811
    # keyframe targets 0, 0.5 and 1.5 m ahead of a robot that stands still; a keyframe-error termination
    # at 0.3 m (max over bodies) ends the last two at the first keyframe
    offsets = np.zeros_like(data.keyframe_offsets)
    offsets[1, :, 0], offsets[2, :, 0] = 0.5, 1.5
    ahead = dataclasses.replace(data, psi=np.array([0.0, 0.5, 1.5]), keyframe_offsets=offsets)
    first_crossing = {}
    for judge in ("success_test", "termination"):
        cfg = quiet_cfg(sampling={"mode": "adaptive", "uniform_ratio": 0.0, "rate": 1.0, "judge": judge},
                        terminations={"keyframe_error": {"start": 0.3, "min": 0.3, "max": 0.3}})
        env = TrackingEnv(cfg, ahead, num_envs=3)
        env.reset()
        env.sample[:] = torch.tensor([0, 1, 2])
        env.sampler.failure_rate[:] = 0.5
        for _ in range(FRAMES):
            _, _, term, trunc, info = env.step(torch.zeros(3, env.action_dim))
            if info["keyframe_crossed"].any():
                break
        assert term.tolist() == [False, True, True] and not info["terminated_by"]["base_height"].any()
        first_crossing[judge] = env.sampler.failure_rate.tolist()
        for _ in range(FRAMES):  # world 0's episode, and any later one of sample 0, ends at the clip's end
            env.step(torch.zeros(3, env.action_dim))
        assert env.sampler.failure_rate[0] == 0.0  # finished with every keyframe on target: a success
    # 0.5 m off is within the evaluation's 1 m: the termination cut that episode short and it is not judged;
    # 1.5 m off fails the test. Judged by termination, both count as failures.
    assert first_crossing["success_test"] == [0.5, 0.5, 1.0]
    assert first_crossing["termination"] == [0.5, 1.0, 1.0]


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
                                      ({"rate": 0.0}, "sampling.rate"),
                                      ({"demotion": "never"}, "sampling.demotion"),
                                      ({"relative_ratio": 0.0}, "sampling.relative_ratio"),
                                      ({"level_rate": 1.5}, "sampling.level_rate"),
                                      ({"judge": "falls"}, "sampling.judge"),
                                      ({"uniform_share": -0.1}, "sampling.uniform_share"),
                                      ({"success_threshold_m": 0.0}, "sampling.success_threshold_m")])
def test_bad_sampling_values_name_the_key(raw, key):
    with pytest.raises(PipelineInputError, match=key.replace(".", r"\.")):
        EnvConfig.from_dict({"sampling": raw})
