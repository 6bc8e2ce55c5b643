"""The balance policy's catch estimate at a chain's handoff (envs/handoff_catch.py) and a task env paid
with it: its observation is the balance env's own, it tells the landings the balance policy holds from
those it drops, and an episode paid with it ends at the handoff."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.handoff_catch import Handoff, HandoffCatch
from pipeline.envs.tracking_env import TrackingEnv
from pipeline.robot.g1 import default_qpos, load_robot_config

from env_stand_clip import FRAMES, KEYFRAMES, N, data, hold, quiet_cfg  # noqa: F401  (data: the module fixture)

REPO = Path(__file__).resolve().parent.parent
CATCHER = REPO / "models/pretrained/balance_far_jump"
CHECKPOINT = CATCHER / "train" / "policy"


def _catch() -> HandoffCatch:
    return HandoffCatch(CHECKPOINT, torch.tensor(load_robot_config().default_joint_pos, dtype=torch.float32))


def _handoff_starts_env(num_envs: int):
    """The far jump's catcher in its own env, every world started in one of the recorded handoff states,
    on the nominal model without pushes."""
    import yaml

    from pipeline.balance.config import BalanceConfig
    from pipeline.balance.train import make_balance_env

    cfg = BalanceConfig.from_dict(yaml.safe_load((CATCHER / "params.yaml").read_text())["balance"])
    env_cfg = copy.deepcopy(cfg.env)
    env_cfg.randomization.enabled = False
    env_cfg.randomization.push.max_vel_xy = 0.0
    env_cfg.episode_s = 5.0
    env_cfg.starts.drop_prob, env_cfg.starts.states_prob, env_cfg.starts.state_vel_scale = 0.0, 1.0, [1.0, 1.0]
    torch.manual_seed(0)
    return make_balance_env(cfg, CATCHER, num_envs=num_envs, env_cfg=env_cfg)


def test_the_catch_reads_a_state_as_the_balance_env_reads_a_recorded_start():
    env = _handoff_starts_env(8)
    obs = env.reset()
    catch = _catch()
    seen = catch.observation(env.backend.qpos.clone(), env.backend.qvel.clone(), torch.zeros(8))
    assert seen.shape == obs["critic"].shape
    assert torch.allclose(seen, obs["critic"], atol=1e-6)


def test_the_catch_tells_the_landings_the_balance_policy_holds_from_those_it_drops():
    """On the far jump's recorded handoffs: the states the catcher holds for 3 s score higher than those
    it drops, nearly always (AUC); the stance at rest scores near 1, a 50° forward pitch near 0."""
    from pipeline.rl.checkpoint import load_policy

    env = _handoff_starts_env(128)
    obs = env.reset()
    catch = _catch()(env.backend.qpos.clone(), env.backend.qvel.clone(), torch.zeros(128)).numpy()
    policy, _ = load_policy(CHECKPOINT)
    fell = torch.zeros(128, dtype=torch.bool)
    with torch.no_grad():
        for _ in range(int(round(3.0 / env.control_dt))):
            obs, _, terminated, _, _ = env.step(policy(obs["actor"])[0])
            fell |= terminated
    held = ~fell.numpy()
    assert 0 < held.sum() < 128
    auc = (catch[held][:, None] > catch[~held][None, :]).mean()
    assert auc > 0.9, auc
    assert ((catch >= 0) & (catch <= 1)).all()

    qpos = torch.tensor(default_qpos(load_robot_config()), dtype=torch.float32)[None].repeat(2, 1)
    qpos[1, 3:7] = torch.tensor([np.cos(0.44), 0.0, np.sin(0.44), 0.0])  # pitched 50° forward
    stance, pitched = _catch()(qpos, torch.zeros(2, 33), torch.zeros(2)).tolist()
    assert stance > 0.8 and pitched < 0.2


def test_the_catch_refuses_what_is_not_a_balance_policy_checkpoint(tmp_path):
    default = torch.zeros(27)
    with pytest.raises(PipelineInputError, match="config.json"):
        HandoffCatch(tmp_path, default)
    with pytest.raises(PipelineInputError, match="obs_layout"):  # a task policy's export: no balance layout
        HandoffCatch(REPO / "models/pretrained/far_jump/export", default)


def test_a_task_paid_at_the_handoff_ends_there(data):
    """Standing through the clip with a handoff at the middle keyframe: the episode ends on the step that
    crosses it, paid the keyframe and `handoff_catch` times the catch of the state (a stand: near 1); no
    reference-state start at or after it. Unpaid, the same episode runs to the phase's end."""
    handoff = Handoff(phase=KEYFRAMES[1] / (FRAMES - 1), balance_checkpoint=CHECKPOINT)
    ended, paid = {}, {}
    for weight in (0.0, 100.0):
        env = TrackingEnv(quiet_cfg(rewards={"weights": {"handoff_catch": weight}}), data, num_envs=N, handoff=handoff)
        torch.manual_seed(0)
        env.reset()
        for step in range(1, 2 * FRAMES):
            _, rewards, terminated, truncated, info = env.step(hold(env))
            assert not terminated.any()
            if step == KEYFRAMES[1]:
                assert info["keyframe_index"].eq(1).all()  # the handoff's own keyframe is crossed and paid
                paid[weight] = rewards["sparse"]
                logged = info.get("handoff_catch")
            elif weight:
                assert info["handoff_catch"].isnan().all()  # no handoff this step
            if truncated.all():
                break
        ended[weight] = step
    assert ended[0.0] == FRAMES - 1 and ended[100.0] == KEYFRAMES[1]
    catch = paid[100.0] - paid[0.0]
    assert torch.all(catch > 80.0) and torch.all(catch <= 100.0 + 1e-3), catch
    assert torch.allclose(logged * 100.0, catch, atol=1e-3)  # what the training log averages

    rsi = TrackingEnv(quiet_cfg(rewards={"weights": {"handoff_catch": 1.0}}, rsi_prob=1.0), data, num_envs=N,
                      handoff=handoff)
    assert rsi.rsi_frame_table.max() < KEYFRAMES[1]


def test_a_task_paid_at_the_handoff_needs_one(data):
    with pytest.raises(PipelineInputError, match="rewards.weights.handoff_catch"):
        TrackingEnv(quiet_cfg(rewards={"weights": {"handoff_catch": 1.0}}), data, num_envs=N)


def test_the_evaluate_stage_scores_the_whole_task_unpaid():
    from pipeline.evaluation.config import EvalConfig
    from pipeline.evaluation.evaluate import evaluation_env_config

    cfg = quiet_cfg(rewards={"weights": {"handoff_catch": 300.0}})
    assert evaluation_env_config(cfg, EvalConfig()).rewards.weights.handoff_catch == 0.0
    assert cfg.rewards.weights.handoff_catch == 300.0


def test_the_training_log_averages_the_catch_of_the_episodes_handed_over():
    from pipeline.rl.episode_stats import EpisodeStats

    stats = EpisodeStats(3, "cpu")
    ended = torch.tensor([True, True, False])
    info = {"handoff_catch": torch.tensor([0.4, float("nan"), float("nan")]),
            "terminated_by": {"tilt": torch.tensor([False, True, False])}}
    stats.step({"sparse": torch.ones(3), "dense": torch.ones(3)}, torch.tensor([False, True, False]),
               torch.tensor([True, False, False]), info)
    assert ended.sum() == len(stats.finished)
    assert stats.summary()["handoff_catch"] == pytest.approx(0.4)  # the fall (NaN) is not averaged in
    assert "handoff_catch" not in EpisodeStats(1, "cpu").summary()
