"""Trainer checkpoints on the toy keyframe env (tests/toy_keyframe_env.py): resuming bit for bit, warm starts,
weight averaging, curricula counted in iterations, the history, and checkpoints refused for another robot or layout."""

from __future__ import annotations

import json

import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.rl.averaging import WeightAverage
from pipeline.rl.checkpoint import load_policy, save_policy
from pipeline.rl.trainer import Trainer
from pipeline.rl.training import train_stage2

from toy_keyframe_env import META, ToyKeyframeEnv, make_stage1, small_cfg

torch.set_num_threads(1)


def _trainer(run_dir, cfg, seed):
    torch.manual_seed(seed)
    env = ToyKeyframeEnv(cfg.ppo.num_envs)
    policy, critic = make_stage1(env, cfg, seed)
    return Trainer(env, policy, critic, cfg, run_dir, stage=1, meta=META, l2c2=True, tensorboard=False, progress=False)


@pytest.mark.parametrize("noise_correlation", [0.0, 0.9])
def test_resume_reproduces_the_next_iteration_bit_for_bit(tmp_path, noise_correlation):
    cfg = small_cfg(save_interval=2, ppo={"num_envs": 32, "steps_per_iteration": 8, "epochs": 2, "minibatches": 2,
                                          "noise_correlation": noise_correlation})
    straight = _trainer(tmp_path / "a", cfg, seed=0)
    straight.run(3)
    interrupted = _trainer(tmp_path / "b", cfg, seed=0)
    interrupted.run(2)  # "killed" after the checkpoint at iteration 2
    resumed = _trainer(tmp_path / "b", cfg, seed=99)  # different init: everything must come from disk
    resumed.run(3, resume=True)
    for (k, a), b in zip(straight.policy.state_dict().items(), resumed.policy.state_dict().values()):
        assert torch.equal(a, b), k
    for a, b in zip(straight.critic.state_dict().values(), resumed.critic.state_dict().values()):
        assert torch.equal(a, b)
    assert straight.ppo.learning_rate == resumed.ppo.learning_rate
    assert [h["policy_loss"] for h in straight.history] == [h["policy_loss"] for h in resumed.history]


def test_a_new_run_in_a_used_folder_leaves_nothing_of_the_old_run_to_resume(tmp_path):
    """A run started without --resume where another run finished: the old run's checkpoints and its finished
    metrics go, so a --resume after this run's first chunk continues this run, not the old one."""
    cfg = small_cfg(save_interval=2, ppo={"num_envs": 32, "steps_per_iteration": 8, "epochs": 2, "minibatches": 2})
    _trainer(tmp_path / "run", cfg, seed=0).run(6)
    assert (tmp_path / "run" / "metrics.json").is_file()
    assert (tmp_path / "run" / "checkpoints" / "latest").read_text().strip() == "iter_000006"
    (tmp_path / "run" / "tensorboard").mkdir()
    (tmp_path / "run" / "tensorboard" / "events.out.tfevents.old").write_text("the old run's curves")
    again = _trainer(tmp_path / "run", cfg, seed=1)
    assert again.run(6, chunk_s=0.0)["paused"]  # stops at its first checkpoint, iteration 2
    assert (tmp_path / "run" / "checkpoints" / "latest").read_text().strip() == "iter_000002"
    assert sorted(p.name for p in (tmp_path / "run" / "checkpoints").glob("iter_*")) == ["iter_000002"]
    assert not (tmp_path / "run" / "metrics.json").exists() and not (tmp_path / "run" / "tensorboard").exists()
    resumed = _trainer(tmp_path / "run", cfg, seed=99)
    resumed.run(6, resume=True)
    assert [h["iteration"] for h in resumed.history][:2] == [1, 2] and resumed.history[-1]["iteration"] == 6


def test_a_warm_start_takes_the_networks_and_optimiser_but_counts_its_own_iterations(tmp_path):
    cfg = small_cfg(save_interval=2, ppo={"num_envs": 32, "steps_per_iteration": 8, "epochs": 2, "minibatches": 2})
    first = _trainer(tmp_path / "a", cfg, seed=0)
    first.run(2)
    tuned = _trainer(tmp_path / "b", cfg, seed=99)  # another init: what it starts from must come from the run
    assert not all(torch.equal(a, b) for a, b in zip(first.policy.state_dict().values(),
                                                      tuned.policy.state_dict().values()))
    tuned.warm_start(tmp_path / "a")
    for (k, a), b in zip(first.policy.state_dict().items(), tuned.policy.state_dict().values()):
        assert torch.equal(a, b), k
    for a, b in zip(first.critic.state_dict().values(), tuned.critic.state_dict().values()):
        assert torch.equal(a, b)
    assert tuned.ppo.learning_rate == first.ppo.learning_rate
    tuned.run(1)
    assert [h["iteration"] for h in tuned.history] == [1]
    with pytest.raises(PipelineInputError, match="training_state.pt"):
        tuned.warm_start(tmp_path / "nowhere")


def test_a_warm_start_from_a_committed_run_takes_its_final_networks(tmp_path):
    """A committed run keeps `policy/` (networks, normalisers, critic) and not its checkpoints: a fine-tune
    from it starts from those networks with a fresh optimiser."""
    import shutil

    cfg = small_cfg(save_interval=2, ppo={"num_envs": 32, "steps_per_iteration": 8, "epochs": 2, "minibatches": 2})
    first = _trainer(tmp_path / "a", cfg, seed=0)
    first.run(2)
    shutil.rmtree(tmp_path / "a" / "checkpoints")  # as committed under models/pretrained/<name>/train
    tuned = _trainer(tmp_path / "b", cfg, seed=99)
    tuned.warm_start(tmp_path / "a")
    for (k, a), b in zip(first.policy.state_dict().items(), tuned.policy.state_dict().values()):
        assert torch.equal(a, b), k
    for a, b in zip(first.critic.state_dict().values(), tuned.critic.state_dict().values()):
        assert torch.equal(a, b)
    tuned.run(1)
    assert [h["iteration"] for h in tuned.history] == [1]


def test_weight_average_means_floats_and_keeps_the_latest_of_the_rest():
    average = WeightAverage()
    average.add({"w": torch.tensor([1.0, 2.0]), "n": torch.tensor(3)})
    average.add({"w": torch.tensor([3.0, 6.0]), "n": torch.tensor(5)})
    mean = average.mean()
    assert torch.equal(mean["w"], torch.tensor([2.0, 4.0])) and mean["w"].dtype == torch.float32
    assert mean["n"].item() == 5
    with pytest.raises(ValueError, match="keys differ"):
        average.add({"w": torch.zeros(2)})


def test_average_tail_writes_the_mean_of_the_last_snapshots_and_survives_a_resume(tmp_path):
    from safetensors.torch import load_file

    cfg = small_cfg(save_interval=1, keep_checkpoints=4, average_tail=0.5, average_every=1,
                    ppo={"num_envs": 16, "steps_per_iteration": 4, "epochs": 1, "minibatches": 1})
    straight = _trainer(tmp_path / "a", cfg, seed=0)
    straight.run(4)
    # iterations 2, 3 and 4 end in the last half of the run; the live policy stays the last iteration's
    snapshots = [load_file(tmp_path / "a" / "checkpoints" / f"iter_{i:06d}" / "model.safetensors") for i in (2, 3, 4)]
    written = load_file(tmp_path / "a" / "policy" / "model.safetensors")
    for key, value in written.items():
        if key.startswith("policy.") and value.is_floating_point():
            want = (sum(s[key].double() for s in snapshots) / 3).to(value.dtype)
            assert torch.allclose(value, want, atol=1e-7), key
    assert not torch.equal(written["policy.body.0.weight"], snapshots[-1]["policy.body.0.weight"])
    assert json.loads((tmp_path / "a" / "policy" / "config.json").read_text())["averaged_snapshots"] == 3

    interrupted = _trainer(tmp_path / "b", cfg, seed=0)
    interrupted.run(3)  # killed after iteration 3's checkpoint, two snapshots into the average
    _trainer(tmp_path / "b", cfg, seed=99).run(4, resume=True)
    resumed = load_file(tmp_path / "b" / "policy" / "model.safetensors")
    for key, value in written.items():
        assert torch.equal(value, resumed[key]), key


@pytest.mark.parametrize("bad", [{"average_tail": -0.1}, {"average_tail": 1.5}, {"average_every": 0}])
def test_bad_average_settings_are_refused(bad):
    with pytest.raises(PipelineInputError, match=next(iter(bad))):
        small_cfg(**bad)


def test_curricula_follow_iterations_not_the_clock(tmp_path, monkeypatch):
    """A time limit only caps a run: on a slow (or busy) machine the same config trains the same policy,
    unless the cap stops it, which the run then reports. Sized by time alone (0 iterations), the curricula
    follow the clock."""
    import pipeline.rl.trainer as trainer_module

    cfg = small_cfg(ppo={"num_envs": 16, "steps_per_iteration": 4, "epochs": 1, "minibatches": 1})
    fast = _trainer(tmp_path / "fast", cfg, seed=0)
    fast.run(4)
    clock = iter(range(0, 10_000, 7))  # every reading 7 s later: 4 iterations take far more than 60 s of "wall time"
    monkeypatch.setattr(trainer_module.time, "time", lambda: float(next(clock)))
    slow = _trainer(tmp_path / "slow", cfg, seed=0)
    metrics = slow.run(4, time_limit_s=1000.0)
    assert slow.env.curriculum_calls == fast.env.curriculum_calls == [0.0, 0.25, 0.5, 0.75]
    for a, b in zip(fast.policy.state_dict().values(), slow.policy.state_dict().values()):
        assert torch.equal(a, b)
    assert metrics["stopped_by_time_limit"] is False

    messages = []
    capped = _trainer(tmp_path / "capped", cfg, seed=0)
    capped.log = messages.append
    metrics = capped.run(4, time_limit_s=20.0)
    assert metrics["iterations"] < 4 and metrics["stopped_by_time_limit"] is True
    assert any("time limit stopped it at iteration" in m for m in messages), messages
    assert json.loads((tmp_path / "capped" / "metrics.json").read_text())["stopped_by_time_limit"] is True

    by_time = _trainer(tmp_path / "by_time", cfg, seed=0)
    metrics = by_time.run(0, time_limit_s=60.0)
    calls = by_time.env.curriculum_calls
    assert metrics["iterations"] == len(calls) >= 2 and calls == sorted(calls) and 0 < calls[-1] <= 1.0
    with pytest.raises(ValueError, match="time limit"):
        _trainer(tmp_path / "none", cfg, seed=0).run(0)


def test_history_splits_each_iteration_into_collection_and_update(tmp_path):
    cfg = small_cfg(ppo={"num_envs": 16, "steps_per_iteration": 4, "epochs": 1, "minibatches": 1})
    trainer = _trainer(tmp_path, cfg, seed=0)
    trainer.run(3)
    for before, h in zip(trainer.history, trainer.history[1:]):
        assert h["collect_seconds"] > 0 and h["update_seconds"] > 0
        assert h["collect_seconds"] + h["update_seconds"] <= h["seconds"] - before["seconds"] + 1e-3



def test_checkpoint_from_another_robot_or_layout_is_refused(tmp_path):
    cfg = small_cfg()
    env = ToyKeyframeEnv(4)
    policy, critic = make_stage1(env, cfg)
    save_policy(tmp_path / "p", policy, critic, META)
    load_policy(tmp_path / "p", {"robot": "toy", "obs_layout": META["obs_layout"], "actor_obs_dim": 3})
    with pytest.raises(PipelineInputError, match="robot"):
        load_policy(tmp_path / "p", {"robot": "unitree_g1"})
    with pytest.raises(PipelineInputError, match="obs_layout"):
        load_policy(tmp_path / "p", {"robot": "toy", "obs_layout": {"pos": 2, "phase": 1, "psi": 1}})
    with pytest.raises(PipelineInputError, match="not a policy folder"):
        load_policy(tmp_path / "missing")
    # A policy saved before `action_offset` existed was trained around the default pose.
    load_policy(tmp_path / "p", {"robot": "toy", "action_offset": "default"})
    with pytest.raises(PipelineInputError, match="action_offset"):
        load_policy(tmp_path / "p", {"robot": "toy", "action_offset": "reference"})
    save_policy(tmp_path / "r", policy, critic, META | {"action_offset": "reference"})
    with pytest.raises(PipelineInputError, match="action_offset"):
        load_policy(tmp_path / "r", {"robot": "toy", "action_offset": "default"})


def test_stage2_without_stage1_checkpoint_is_refused(tmp_path):
    cfg = small_cfg()
    with pytest.raises(PipelineInputError, match="stage-1"):
        train_stage2(None, None, cfg, tmp_path / "s2", stage1_dir=tmp_path / "nothing", env=ToyKeyframeEnv(4))
    assert not (tmp_path / "s2").exists()
