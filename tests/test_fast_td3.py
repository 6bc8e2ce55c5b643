"""The off-policy trainer (train.algorithm: fast_td3), its replay buffer and the left-right mirror on the tracking env.

Learning and resume run on the toy keyframe env of tests/toy_keyframe_env.py (sparse keyframe rewards + dense
tracking, TrackingEnv's contract); the mirror itself is tested in tests/test_mirror.py.
"""

from __future__ import annotations

import json

import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.rl.checkpoint import load_policy
from pipeline.rl.config import TrainConfig
from pipeline.rl.fast_td3 import build_fast_td3_trainer
from pipeline.rl.mirror import Mirror
from pipeline.rl.replay_buffer import ReplayBuffer
from pipeline.rl.trainer import Trainer
from pipeline.rl.training import train, train_stage2
from env_stand_clip import data  # noqa: F401  (the module fixture: a 61-frame standing clip, 3 keyframes)
from toy_keyframe_env import META, ToyKeyframeEnv, evaluate, make_stage1, small_cfg

torch.set_num_threads(1)


def td3_cfg(**over) -> TrainConfig:
    fast = {"num_envs": 64, "steps_per_iteration": 16, "updates_per_step": 2, "batch_size": 512,
            "buffer_size": 64 * 256, "learning_starts": 4, "critic_learning_rate": 1e-3, "action_bound": 1.0,
            "reward_scale_sparse": 0.1, "reward_scale_dense": 0.1, "exploration_std_max": 0.4}
    fast.update(over.pop("fast_td3", {}))
    raw = {"algorithm": "fast_td3", "network": {"actor_hidden": [64, 64], "critic_hidden": [64, 64]},
           "fast_td3": fast, "save_interval": 100}
    raw.update(over)
    return TrainConfig.from_dict(raw)


def td3_trainer(run_dir, cfg, seed=0):
    torch.manual_seed(seed)
    env = ToyKeyframeEnv(cfg.fast_td3.num_envs)
    return build_fast_td3_trainer(env, None, cfg, run_dir, env.dphi, tensorboard=False, progress=False, log=lambda *_: None)


# ------------------------------------------------------------------------------------------ learning
def test_fast_td3_improves_return_on_toy_keyframe_task(tmp_path):
    # 4 updates per env step: at 2, the return after 40 iterations ranged 5-17 over seeds 1-4; at 4, 19-25
    trainer = td3_trainer(tmp_path, td3_cfg(fast_td3={"updates_per_step": 4}), seed=0)
    before = evaluate(trainer.policy)
    metrics = trainer.run(40)
    after = evaluate(trainer.policy)
    # The optimum is ~20 sparse + ~5 dense; doing nothing scores ~3 (the same bar as PPO's test).
    assert after > before + 8.0, (before, after)
    assert after > 15.0, after
    assert metrics["success_rate"] is not None
    # the saved policy is the deterministic actor, readable as any stage-1 policy
    loaded, meta = load_policy(tmp_path / "policy", {"obs_layout": {"pos": 2, "phase": 1}})
    assert meta["algorithm"] == "fast_td3" and meta["architecture"]["output_bound"] == 1.0
    obs = torch.randn(5, 3)
    assert torch.equal(loaded(obs)[0], trainer.policy.eval()(obs)[0])


def test_stage2_adapters_train_on_a_fast_td3_stage1_policy(tmp_path):
    """Stage 2 is PPO's: its adapters sit on the frozen deterministic actor, which it starts equal to."""
    stage1 = td3_trainer(tmp_path / "s1", td3_cfg(), seed=0)
    stage1.run(2)
    cfg = small_cfg(iterations_stage2=2)
    env = ToyKeyframeEnv(cfg.ppo.num_envs)
    metrics = train_stage2(None, None, cfg, tmp_path / "s2", stage1_dir=tmp_path / "s1" / "policy", env=env,
                           tensorboard=False, progress=False)
    assert metrics["iterations"] == 2
    policy, meta = load_policy(tmp_path / "s2" / "policy")
    assert meta["algorithm"] == "ppo" and meta["stage1_algorithm"] == "fast_td3"
    obs = torch.randn(6, 3)
    zero_phase = torch.zeros(6)
    with torch.no_grad():
        base_action = stage1.policy.eval()(obs)[0]
        assert torch.allclose(policy.compose(obs, zero_phase, torch.randn(6, 2)), base_action)
        assert torch.equal(policy.base(obs)[0], base_action)  # frozen


# ------------------------------------------------------------------------------------------ resume
@pytest.mark.parametrize("mirror", [False, True])
def test_fast_td3_resume_reproduces_the_next_update_bit_for_bit(tmp_path, mirror, monkeypatch):
    """A run stopped after its checkpoint at iteration 2 and resumed computes iteration 3's env steps
    and updates exactly as the uninterrupted run: same weights, target critics, optimiser moments, losses."""
    if mirror:  # the toy env's own left-right mirror: x stays, y flips (its layout names no G1 quantities)
        toy = Mirror(torch.arange(3), torch.tensor([1.0, -1.0, 1.0]), torch.arange(4), torch.tensor([1.0, -1.0, 1.0, 1.0]),
                     torch.arange(2), torch.tensor([1.0, -1.0]))
        monkeypatch.setattr("pipeline.rl.fast_td3.mirror_for_env", lambda env, raw_dim: toy)
    cfg = td3_cfg(save_interval=2, fast_td3={"mirror": mirror, "steps_per_iteration": 6})
    straight = td3_trainer(tmp_path / "a", cfg, seed=0)
    straight.run(3)
    interrupted = td3_trainer(tmp_path / "b", cfg, seed=0)
    interrupted.run(2)
    resumed = td3_trainer(tmp_path / "b", cfg, seed=99)  # other initial weights: everything must come from disk
    resumed.run(3, resume=True)
    for module in ("policy", "critic"):
        for (k, a), b in zip(getattr(straight, module).state_dict().items(), getattr(resumed, module).state_dict().values()):
            assert torch.equal(a, b), (module, k)
    for a, b in zip(straight.td3.target.state_dict().values(), resumed.td3.target.state_dict().values()):
        assert torch.equal(a, b)
    assert straight.td3.updates == resumed.td3.updates
    for key in ("critic_loss", "actor_loss", "q_sparse"):
        assert [h[key] for h in straight.history] == [h[key] for h in resumed.history], key
    assert straight.history[-1]["buffer_transitions"] == resumed.history[-1]["buffer_transitions"]


def test_fast_td3_resume_without_the_buffer_refills_before_updating(tmp_path):
    cfg = td3_cfg(save_interval=2, fast_td3={"checkpoint_buffer": False, "steps_per_iteration": 6})
    td3_trainer(tmp_path, cfg).run(2)
    resumed = td3_trainer(tmp_path, cfg, seed=5)
    updates_before = None

    def watch(*args):
        nonlocal updates_before
        updates_before = resumed.td3.updates

    resumed.log = watch
    resumed.run(3, resume=True)
    # 6 steps after the resume; updates start once the buffer holds learning_starts (4) steps: at steps 4, 5 and 6
    assert resumed.td3.updates == updates_before + 3 * cfg.fast_td3.updates_per_step
    assert resumed.history[-1]["buffer_transitions"] == 6 * cfg.fast_td3.num_envs


# ------------------------------------------------------------------------------------------ bad input
def test_unknown_algorithm_is_refused():
    with pytest.raises(PipelineInputError, match="algorithm.*unknown algorithm 'sac'"):
        TrainConfig.from_dict({"algorithm": "sac"})
    with pytest.raises(PipelineInputError, match="algorithm"):
        TrainConfig.from_dict({"algorithm": "fast_td3", "variant": "amp_style"})
    with pytest.raises(PipelineInputError, match="fast_td3.learning_starts"):
        TrainConfig.from_dict({"algorithm": "fast_td3", "fast_td3": {"n_step": 5, "learning_starts": 2}})


def test_resume_across_algorithms_is_refused_before_training(tmp_path):
    cfg = small_cfg(save_interval=1, ppo={"num_envs": 16, "steps_per_iteration": 4})
    env = ToyKeyframeEnv(16)
    policy, critic = make_stage1(env, cfg)
    trainer = td3_trainer(tmp_path, td3_cfg())
    ppo_meta = dict(trainer.meta, algorithm="ppo")  # the same robot, joints and layout: only the algorithm differs
    Trainer(env, policy, critic, cfg, tmp_path, stage=1, meta=ppo_meta, tensorboard=False, progress=False).run(1)
    with pytest.raises(PipelineInputError, match="algorithm.*'ppo'.*'fast_td3'"):
        trainer.run(2, resume=True)
    assert trainer.history == [] and trainer.td3.updates == 0
    # and the other way round: an off-policy checkpoint under a PPO run
    td3_trainer(tmp_path / "td3", td3_cfg(save_interval=1)).run(1)
    ppo = Trainer(env, policy, critic, cfg, tmp_path / "td3", stage=1, meta=ppo_meta, tensorboard=False, progress=False)
    with pytest.raises(PipelineInputError, match="algorithm"):
        ppo.run(2, resume=True)


def test_resume_from_a_checkpoint_of_another_observation_layout_is_refused(tmp_path):
    td3_trainer(tmp_path, td3_cfg(save_interval=1)).run(1)
    trainer = td3_trainer(tmp_path, td3_cfg())
    trainer.meta = dict(trainer.meta, obs_layout={"pos": 2, "phase": 1, "psi": 1})
    with pytest.raises(PipelineInputError, match="obs_layout"):
        trainer.run(2, resume=True)
    assert trainer.history == []


# ------------------------------------------------------------------------------------------ replay buffer
def test_replay_buffer_n_step_returns_stop_at_episode_ends():
    """One world, five steps: rewards (sparse, dense) = (s, 10 s) at step s; a timeout after step 1 and
    a termination after step 3. Every start is drawn; each one's return, discount and bootstrap
    observation are checked by hand."""
    buf = ReplayBuffer(capacity=8, num_envs=1, critic_dim=1, action_dim=1, device="cpu", actor_dim=1)
    for s in range(5):
        obs = {"critic": torch.tensor([[float(s)]])}
        nxt = {"critic": torch.tensor([[s + 0.5]])}
        buf.add(obs, torch.zeros(1, 1), {"sparse": torch.tensor([float(s)]), "dense": torch.tensor([10.0 * s])}, nxt,
                torch.tensor([s == 3]), torch.tensor([s == 1]))
    gammas = {"sparse": 1.0, "dense": 0.5}
    torch.manual_seed(0)
    batch = buf.sample(256, 2, gammas, {"sparse": False, "dense": True})
    seen = set()
    for i in range(256):
        start = int(batch["critic_obs"][i, 0])
        seen.add(start)
        ret_s, ret_d = batch["returns"]["sparse"][i].item(), batch["returns"]["dense"][i].item()
        disc_s, disc_d = batch["discounts"]["sparse"][i].item(), batch["discounts"]["dense"][i].item()
        boot = batch["next_critic_obs"][i, 0].item()
        want = {
            0: (0 + 1, 0 + 0.5 * 10, 0.0, 0.5 * 0.5, 1.5),   # 0 -> 1, timeout after 1: sparse stops, dense bootstraps
            1: (1, 10, 0.0, 0.5, 1.5),                        # the timeout step alone
            2: (2 + 3, 20 + 0.5 * 30, 0.0, 0.0, 3.5),         # 2 -> 3, terminated after 3: neither bootstraps
            3: (3, 30, 0.0, 0.0, 3.5),
        }[start]
        assert (ret_s, ret_d, disc_s, disc_d, boot) == pytest.approx(want), start
    assert seen == {0, 1, 2, 3}  # step 4's two-step return is not held yet


# ------------------------------------------------------------------------------------------ chunks
@pytest.mark.parametrize("algorithm", ["ppo", "fast_td3"])
def test_a_run_in_chunks_trains_what_one_run_trains(tmp_path, algorithm, monkeypatch):
    """Chunks of (nearly) zero seconds stop at every checkpoint; resumed until done they give the
    uninterrupted run's weights, and the wall-time cap counts the chunks' time together."""
    if algorithm == "ppo":
        cfg = small_cfg(save_interval=2, ppo={"num_envs": 16, "steps_per_iteration": 4, "epochs": 1, "minibatches": 2})

        def make(run_dir, seed):
            torch.manual_seed(seed)
            env = ToyKeyframeEnv(16)
            policy, critic = make_stage1(env, cfg, seed)
            return Trainer(env, policy, critic, cfg, run_dir, stage=1, meta=META, tensorboard=False,
                           progress=False, log=lambda *_: None)
    else:
        cfg = td3_cfg(save_interval=2, fast_td3={"steps_per_iteration": 6})

        def make(run_dir, seed):
            return td3_trainer(run_dir, cfg, seed)

    straight = make(tmp_path / "a", 0)
    straight.run(6)
    first = make(tmp_path / "b", 0)
    paused = first.run(6, chunk_s=0.0)
    assert paused == {"stage": 1, "paused": True, "iteration": 2, "train_seconds": first.history[-1]["seconds"],
                      "checkpoint": str(tmp_path / "b" / "checkpoints" / "iter_000002")}
    assert not (tmp_path / "b" / "policy").exists()
    chunks = 1
    while True:
        result = make(tmp_path / "b", 100 + chunks).run(6, resume=True, chunk_s=0.0)
        chunks += 1
        if not result.get("paused"):
            break
    assert chunks == 3 and result["iterations"] == 6
    final, _ = load_policy(tmp_path / "b" / "policy")
    for (k, a), b in zip(straight.policy.state_dict().items(), final.state_dict().values()):
        assert torch.equal(a, b), k
    # the wall clock counts on across chunks: each chunk's first iteration reads later than the last one's
    seconds = [h["seconds"] for h in json.loads((tmp_path / "b" / "history.json").read_text())]
    assert seconds == sorted(seconds)
    # and a cap the earlier chunks have spent stops the next chunk after one iteration
    make(tmp_path / "c", 0).run(6, chunk_s=0.0)
    trainer = make(tmp_path / "c", 1)
    result = trainer.run(6, resume=True, time_limit_s=1e-9)
    assert result["iterations"] == 3 and result["stopped_by_time_limit"]


def test_a_chunk_that_ends_in_stage1_does_not_start_stage2(tmp_path):
    cfg = small_cfg(save_interval=2, iterations_stage1=4, iterations_stage2=2,
                    ppo={"num_envs": 16, "steps_per_iteration": 4, "epochs": 1, "minibatches": 2})
    metrics = train(None, None, cfg, tmp_path, env=ToyKeyframeEnv(16), chunk_s=0.0, tensorboard=False, progress=False,
                    log=lambda *_: None)
    assert metrics["paused"] and metrics["iteration"] == 2
    assert not (tmp_path / "stage2").exists() and not (tmp_path / "stage1" / "policy").exists()


# ------------------------------------------------------------------------------------------ on the TrackingEnv
def test_fast_td3_with_the_mirror_on_the_tracking_env_resumes_bit_for_bit(tmp_path, data):  # noqa: F811
    from pipeline.envs.tracking_env import TrackingEnv
    from test_env_resume import noisy_cfg

    cfg = td3_cfg(save_interval=1, network={"actor_hidden": [32], "critic_hidden": [32]},
                  fast_td3={"num_envs": 8, "steps_per_iteration": 6, "batch_size": 64, "buffer_size": 8 * 32,
                            "mirror": True, "action_bound": 3.0})

    def trainer(run_dir, seed):
        torch.manual_seed(seed)
        env = TrackingEnv(noisy_cfg(), data, num_envs=8)
        return build_fast_td3_trainer(env, data, cfg, run_dir, env.dphi, tensorboard=False, progress=False,
                                      log=lambda *_: None)

    straight = trainer(tmp_path / "a", 0)
    assert straight.buffer.actor_is_prefix and straight.td3.mirror is not None
    straight.run(2)
    trainer(tmp_path / "b", 0).run(1)
    resumed = trainer(tmp_path / "b", 99)
    resumed.run(2, resume=True)
    for (k, a), b in zip(straight.policy.state_dict().items(), resumed.policy.state_dict().values()):
        assert torch.equal(a, b), k
    assert straight.history[-1]["critic_loss"] == resumed.history[-1]["critic_loss"]
    assert straight.history[-1]["reward_dense"] == resumed.history[-1]["reward_dense"]
