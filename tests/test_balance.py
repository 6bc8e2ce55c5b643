"""The balance env on the shared RobotEnv: proprioception only, held arms, starts, pushes, randomisation,
its curriculum and resume; the balance policy's export and its config errors."""

import copy
import json

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.balance_config import ARM_JOINTS, BalanceEnvConfig
from pipeline.envs.balance_env import BalanceEnv
from pipeline.envs.robot_env import RobotEnv, proprio_dim
from pipeline.robot.g1 import load_robot_config

QUIET = {"randomization": {"enabled": False}, "starts": {"drop_prob": 0.0, "joint_pos_noise": 0.0,
                                                         "lin_vel_noise": 0.0, "ang_vel_noise": 0.0}}


def _env(raw=None, n=4, states=None):
    torch.manual_seed(0)
    return BalanceEnv(BalanceEnvConfig.from_dict(raw or {}), num_envs=n, start_states=states)


def test_observes_proprioception_only_and_shares_the_tracking_envs_base():
    from pipeline.envs.tracking_env import TrackingEnv

    env = _env(QUIET)
    assert isinstance(env, RobotEnv) and issubclass(TrackingEnv, RobotEnv)
    obs = env.reset()
    assert obs["actor"].shape == (4, 5 * proprio_dim(27)) and env.actor_obs_dim == 435
    layout = env.obs_layout()
    assert list(layout["actor_frame"]) == ["base_ang_vel", "projected_gravity", "joint_pos_rel", "joint_vel", "prev_action"]
    frame = obs["actor"].reshape(4, 5, -1)[:, -1]
    assert torch.allclose(frame[:, 3:6], torch.tensor([0.0, 0.0, -1.0]).expand(4, 3), atol=1e-6)  # upright at the stance


def test_arms_are_held_whatever_the_policy_asks():
    robot = load_robot_config()
    arms = [robot.joint_names.index(j) for j in ARM_JOINTS]
    still, waving = _env(QUIET, n=1), _env(QUIET, n=1)
    still.reset(), waving.reset()
    action = torch.zeros(1, 27)
    action[:, arms] = 3.0
    for _ in range(5):
        still.step(torch.zeros(1, 27))
        waving.step(action)
    assert torch.equal(still.backend.qpos, waving.backend.qpos)


def test_pushes_kick_the_base():
    quiet = copy.deepcopy(QUIET)
    pushed = {"randomization": {"enabled": True, **{k: {"enabled": False} for k in (
        "trunk_mass_add", "base_com_offset", "link_mass_scale", "friction", "restitution", "p_gain_scale",
        "d_gain_scale", "motor_strength", "control_delay_ms")}, "push": {"interval_s": [0.02, 0.02], "max_vel_xy": 0.5}},
              "starts": quiet["starts"]}
    a, b = _env(quiet, n=8), _env(pushed, n=8)
    a.reset(), b.reset()
    a.step(torch.zeros(8, 27))
    b.step(torch.zeros(8, 27))
    kick = (b.backend.qvel[:, 0:2] - a.backend.qvel[:, 0:2]).norm(dim=-1)
    assert kick.max() > 0.1 and kick.max() <= 0.5 * 2**0.5 + 0.05


def test_randomization_differs_between_worlds():
    env = _env({}, n=6)
    env.reset()
    masses = np.array(env.backend.get_model_field("body_mass", np.arange(6)))
    assert np.ptp(masses[:, env.randomizer.trunk]) > 0.1


def test_starts_in_recorded_states_and_curriculum_scales_them():
    robot = load_robot_config()
    state = np.concatenate([[0.0, 0.0, 0.7, 1.0, 0.0, 0.0, 0.0], robot.default_joint_pos])
    qvel = np.zeros(33)
    qvel[0] = 1.0
    states = {"qpos": state[None], "qvel": qvel[None]}
    env = _env({"starts": {"states_prob": 1.0, "drop_prob": 0.0, "state_vel_scale": [1.0, 1.0]},
                "randomization": {"enabled": False}}, n=8, states=states)
    env.reset()
    assert torch.allclose(env.backend.qvel[:, 0], torch.ones(8)) and torch.allclose(env.backend.qpos[:, 2], torch.full((8,), 0.7))
    assert env.update_curriculum(0.0) == 0.0 and env.push_scale == 0.0 and env.delay_scale == 0.0
    env.reset()  # at difficulty 0: no recorded start, the stance (its noise is at most 0.3 m/s)
    assert (env.backend.qvel[:, 0].abs() <= 0.3 + 1e-6).all() and torch.allclose(env.backend.qpos[:, 2], torch.full((8,), 0.76))
    assert env.update_curriculum(1.0) == 1.0


def test_resume_repeats_the_next_steps_bit_for_bit():
    env = _env({}, n=4)
    env.reset()
    for _ in range(3):
        env.step(torch.randn(4, 27) * 0.3)
    saved, rng = env.state_dict(), torch.get_rng_state()
    actions = [torch.randn(4, 27) * 0.3 for _ in range(5)]
    first = [env.step(a)[0]["critic"] for a in actions]
    fresh = _env({}, n=4)
    fresh.load_state_dict(saved)
    torch.set_rng_state(rng)
    again = [fresh.step(a)[0]["critic"] for a in actions]
    assert all(torch.equal(x, y) for x, y in zip(first, again))


def test_bad_config_names_the_key():
    with pytest.raises(PipelineInputError, match="frozen_joints.*unknown joints"):
        BalanceEnvConfig.from_dict({"frozen_joints": ["tail_joint"]})
    with pytest.raises(PipelineInputError, match="starts"):
        BalanceEnvConfig.from_dict({"starts": {"states_prob": 0.8, "drop_prob": 0.5}})
    from pipeline.balance.config import BalanceConfig

    with pytest.raises(PipelineInputError, match="balance.*iterations"):
        BalanceConfig.from_dict({"iterations": -1})
    with pytest.raises(PipelineInputError, match="balance.*unknown key"):
        BalanceConfig.from_dict({"iteration": 3})


def test_trains_exports_and_measures_a_tiny_run(tmp_path):
    """Two PPO iterations through the stage's own functions: a policy, its export (parity), standing rates."""
    from pipeline.balance.config import BalanceConfig
    from pipeline.balance.evaluate import standing_rate
    from pipeline.balance.export import export_balance
    from pipeline.balance.train import train_balance
    from pipeline.rl.checkpoint import load_policy

    cfg = BalanceConfig.from_dict({"iterations": 2, "start_states": "", "train": {
        "ppo": {"num_envs": 8, "steps_per_iteration": 4}, "save_interval": 1}})
    metrics = train_balance(cfg, tmp_path / "train", root=tmp_path, progress=False, tensorboard=False)
    assert metrics["iterations"] == 2
    result = export_balance(cfg, tmp_path / "train" / "policy", tmp_path / "export")
    assert result.parity_max_abs_diff < 1e-5
    meta = json.loads((tmp_path / "export" / "policy.json").read_text())
    assert meta["kind"] == "balance"
    assert {t["name"] for t in meta["observation"]["terms"]}.isdisjoint({"phase", "psi", "odometry"})
    policy, _ = load_policy(tmp_path / "train" / "policy")
    rate = standing_rate(policy, cfg, root=tmp_path, episodes=4, seconds=0.2)
    assert rate["episodes"] == 4 and 0.0 <= rate["upright"] <= 100.0 and rate["standing"] <= rate["upright"]


def test_a_fine_tune_starts_from_the_named_run_and_counts_its_own_iterations(tmp_path):
    """`balance.init_from` names a run folder: the fine-tune starts from its latest checkpoint and counts its own
    iterations (tests/test_rl_checkpoints.py checks the weights it starts from); a folder without a checkpoint is refused."""
    from pipeline.balance.config import BalanceConfig
    from pipeline.balance.train import train_balance

    tiny = {"start_states": "", "train": {"ppo": {"num_envs": 8, "steps_per_iteration": 4}, "save_interval": 1}}
    train_balance(BalanceConfig.from_dict({"iterations": 2, **tiny}), tmp_path / "first", root=tmp_path,
                  progress=False, tensorboard=False)
    log = []
    metrics = train_balance(BalanceConfig.from_dict({"iterations": 1, "init_from": "first", **tiny}),
                            tmp_path / "second", root=tmp_path, progress=False, tensorboard=False, log=log.append)
    assert metrics["iterations"] == 1
    assert any("warm start from" in line and "iter_000002" in line for line in log)
    with pytest.raises(PipelineInputError, match="init_from"):
        train_balance(BalanceConfig.from_dict({"iterations": 1, "init_from": "nowhere", **tiny}), tmp_path / "third",
                      root=tmp_path, progress=False, tensorboard=False)


def test_the_heading_term_pays_for_facing_where_the_episode_started_only_when_weighted():
    import math

    plain = _env(QUIET, n=2)
    assert "heading" not in plain._dense_term_names()  # weight 0: the sum the earlier policies were trained on
    env = _env({**QUIET, "rewards": {"weights": {"heading": 1.0}}}, n=2)
    assert "heading" in env._dense_term_names()
    env.reset()
    info = env.step(torch.zeros(2, env.action_dim))[4]
    assert torch.allclose(info["terms"]["heading"], torch.ones(2), atol=1e-3)  # still facing the start
    env.start_yaw = torch.tensor([0.0, 0.5])  # as if world 1 had started turned 0.5 rad the other way
    info = env.step(torch.zeros(2, env.action_dim))[4]
    assert info["terms"]["heading"][1] == pytest.approx(math.exp(-0.25 / 0.05), rel=0.05)
