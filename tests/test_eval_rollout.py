"""Evaluation rollouts: a scripted env with known errors, then a real TrackingEnv smoke run."""

import math

import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.evaluation.config import EvalConfig
from pipeline.evaluation.evaluate import PolicyRunner, evaluate_policy, range_mask, rollout, spread_in_ranges
from pipeline.evaluation.metrics import aggregate, endings, episode_metrics, pooled_episodes
from pipeline.evaluation.report import results_table
from env_stand_clip import data, quiet_cfg  # noqa: F401  (a 61-frame standing clip; targets moved forward by ψ)


class ScriptedEnv:
    """Two worlds; world 0 runs 4-step episodes crossing keyframes at steps 2 and 4 with 0.2 m error,
    world 1 falls after 1 step every episode."""

    num_envs = 2

    def reset(self):
        self.t = np.zeros(2, int)
        return {"actor": torch.zeros(2, 3)}

    def step(self, action, dphi=None):
        self.t += 1
        crossed = torch.tensor([self.t[0] in (2, 4), False])
        info = {"keyframe_crossed": crossed, "body_pos_error_w": torch.full((2, 3), 0.2),
                "body_pos_error_local": torch.full((2, 3), 0.01), "joint_acc": torch.ones(2, 5),
                "phase": torch.tensor(self.t / 4.0, dtype=torch.float32), "psi": torch.tensor([1.0, 2.0])}
        truncated = torch.tensor([self.t[0] == 4, False])
        terminated = torch.tensor([False, True])
        self.t[truncated.numpy() | terminated.numpy()] = 0
        return {"actor": torch.zeros(2, 3)}, {}, terminated, truncated, info


def test_rollout_counts_every_world_equally():
    policy = lambda obs: (torch.zeros(obs.shape[0], 27), torch.zeros(obs.shape[0]), None)  # noqa: E731
    records = rollout(ScriptedEnv(), policy, episodes_per_env=3, num_keyframes=2)
    assert len(records) == 6
    by_psi = {1.0: [r for r in records if r.psi == 1.0], 2.0: [r for r in records if r.psi == 2.0]}
    assert len(by_psi[1.0]) == 3 and len(by_psi[2.0]) == 3
    out = aggregate([episode_metrics(r) for r in records])
    assert out["success"] == 50.0  # the falling world never reaches its keyframes
    # this env does not say which check ended world 1's episodes; world 0's ran to their end
    assert [episode_metrics(r).ending for r in by_psi[1.0]] == ["completed"] * 3
    assert [episode_metrics(r).ending for r in by_psi[2.0]] == ["unknown"] * 3
    assert out["e_g_bpe"] == pytest.approx(200.0) and out["e_l_bpe"] == pytest.approx(10.0)
    assert out["e_smth"] == pytest.approx(1.0)


def test_ranges_and_spread():
    assert range_mask(np.array([0.5, 1.0, 1.7, 2.5]), [(0.4, 1.0), (2.0, 3.0)]).tolist() == [True, True, False, True]
    assert spread_in_ranges({"easy": [(1.0, 2.0)]}, ["easy"], 2) == [("easy", 1.25), ("easy", 1.75)]


def test_real_env_smoke_and_bad_range():
    from pipeline.envs.config import EnvConfig
    from pipeline.evaluation.evaluate import default_env_factory
    from pipeline.rl.networks import Stage1Policy
    from pipeline.rl.stage2 import Stage2Policy
    from test_export import _tracking_data

    torch.manual_seed(0)
    data = _tracking_data(frames=40)
    cfg = EvalConfig.from_dict({"episodes_per_range": 2, "runs": 2, "num_envs": 2})
    policy = PolicyRunner(Stage2Policy(Stage1Policy(460, 27, [32], phase_rate=0.03), [16], phase_rate=0.03))
    result = evaluate_policy(policy, data, cfg, default_env_factory(EnvConfig(), cfg))
    assert [len(run["easy"]) for run in result.runs] == [2, 2]
    assert all(1.0 <= e.psi <= 1.5 for run in result.runs for e in run["easy"])
    assert all(1.5 <= e.psi <= 2.0 for run in result.runs for e in run["hard"])
    from pipeline.evaluation.report import metrics_document

    from pipeline.evaluation.run import funnel_rows

    doc = metrics_document("far_jump", "adamimic", result.runs, result.psi_ranges)
    doc["keyframe_funnel"] = funnel_rows(pooled_episodes(result.runs), data, cfg.success_threshold_m)
    assert math.isfinite(doc["ranges"]["overall"]["e_l_bpe"]["mean"])
    assert [r["time_s"] for r in doc["keyframe_funnel"]] == pytest.approx(data.keyframe_frames / data.motion.fps)
    assert doc["keyframe_funnel"][-1]["on_track"] == pytest.approx(doc["ranges"]["overall"]["success"]["mean"])
    doc["endings"] = endings(pooled_episodes(result.runs))
    assert doc["endings"]["episodes"] == 8 and sum(doc["endings"]["ending"].values()) == pytest.approx(100.0)
    assert doc["endings"]["ending"]["unknown"] == 0.0  # the real env always says how an episode ended
    table = results_table({"adamimic": doc})
    assert "| adamimic |" in table and "## adamimic: keyframe by keyframe" in table
    assert f"How the 8 episodes ended: {doc['endings']['ending']['completed']:.0f} % ran to the end" in table
    data.psi_ranges = {"easy": [(5.0, 6.0)], "hard": [(1.5, 2.0)]}
    with pytest.raises(PipelineInputError, match="psi.easy"):
        evaluate_policy(policy, data, cfg, default_env_factory(EnvConfig(), cfg))


def test_evaluation_is_decided_by_its_seed_and_sweeps_psi():
    """Every policy meets the same ψ samples in the same order, each sample of a range equally often;
    the same `seed` gives the same episodes whatever the caller's RNG state, another seed other
    randomised worlds, and the caller's RNG stream is left where it was."""
    import numpy as np

    from pipeline.envs.config import EnvConfig
    from pipeline.evaluation.evaluate import default_env_factory
    from pipeline.rl.networks import Stage1Policy
    from test_export import _tracking_data

    data = _tracking_data(frames=40)

    def evaluate(seed: int, caller_seed: int, policy_seed: int = 0, randomised: bool = False):
        torch.manual_seed(policy_seed)
        policy = PolicyRunner(Stage1Policy(460, 27, [32], phase_rate=0.03))
        cfg = EvalConfig.from_dict({"episodes_per_range": 12, "runs": 1, "num_envs": 4, "seed": seed,
                                    "domain_randomization": randomised})
        torch.manual_seed(caller_seed)
        result = evaluate_policy(policy, data, cfg, default_env_factory(EnvConfig(), cfg))
        return [(e.psi, e.global_error_sum) for name in ("easy", "hard") for e in result.runs[0][name]]

    # 6 samples per range, 4 worlds × 3 episodes: world w's k-th episode is sample (w + 4k) mod 6,
    # kept in (episode, world) order, so each range lists its samples in order, twice
    easy, hard = data.psi[data.psi <= 1.5 + 1e-9], data.psi[data.psi >= 1.5 - 1e-9]
    expected_psi = np.concatenate([easy, easy, hard, hard])
    for policy_seed in (0, 1):  # two policies, whose episodes end at other times
        assert [p for p, _ in evaluate(0, 1, policy_seed)] == pytest.approx(expected_psi.tolist())

    assert evaluate(0, caller_seed=1, randomised=True) == evaluate(0, caller_seed=2, randomised=True)
    assert evaluate(0, caller_seed=1, randomised=True) != evaluate(5, caller_seed=1, randomised=True)
    policy = PolicyRunner(Stage1Policy(460, 27, [32], phase_rate=0.03))
    cfg = EvalConfig.from_dict({"episodes_per_range": 4, "runs": 1, "num_envs": 4, "domain_randomization": True})
    torch.manual_seed(3)
    expected = torch.rand(3)
    torch.manual_seed(3)
    evaluate_policy(policy, data, cfg, default_env_factory(EnvConfig(), cfg))
    assert torch.equal(torch.rand(3), expected)


def test_policy_runner_samples_when_not_deterministic():
    from pipeline.rl.networks import Stage1Policy

    module = Stage1Policy(460, 27, [32], phase_rate=0.03)
    obs = torch.randn(4, 460)
    mean_runner, sampling_runner = PolicyRunner(module), PolicyRunner(module, deterministic=False)
    assert torch.equal(mean_runner(obs)[0], mean_runner(obs)[0])
    first, second = sampling_runner(obs)[0], sampling_runner(obs)[0]
    assert not torch.equal(first, second)
    assert (first - mean_runner(obs)[0]).std() == pytest.approx(1.0, rel=0.2)  # init std exp(0)
    with pytest.raises(PipelineInputError, match="deterministic"):
        PolicyRunner(torch.nn.Linear(460, 27), deterministic=False)


def test_psi_reached_from_a_real_env(data):  # noqa: F811
    """The env's keyframe misses reach the metric: a robot standing on the spot while the test clip's
    keyframe targets move forward by ψ reached ψ = 0 whatever it was asked."""
    from pipeline.envs.tracking_env import TrackingEnv
    from pipeline.evaluation.metrics import PsiReach

    reach = PsiReach.fit(data.psi, data.keyframe_offsets)
    assert reach is not None and reach.slope == pytest.approx(1.0)
    env = TrackingEnv(quiet_cfg(), data, num_envs=3)
    env.termination_threshold = math.inf
    hold = lambda obs: (torch.zeros(obs.shape[0], env.action_dim), None, None)  # noqa: E731
    records = rollout(env, hold, episodes_per_env=1, num_keyframes=data.num_keyframes)
    metrics = [episode_metrics(r, reach=reach) for r in records]
    assert {round(m.psi, 2) for m in metrics} <= {0.0, 0.05, 0.1}
    for m in metrics:
        assert m.success and m.psi_reached == pytest.approx(0.0, abs=0.02)


def test_endings_from_a_real_env(data):  # noqa: F811
    """The env's checks and tilt error reach the metric: an upright robot against a reference that leans
    back past the tilt check fell forward of it, one against a reference leaning forward fell backward, one
    below a reference lifted 1 m (upright) sank, and one left alone ran to the end."""
    from pipeline.envs.tracking_env import TrackingEnv
    from pipeline.evaluation.metrics import endings

    def ending(edit, **cfg) -> list:
        env = TrackingEnv(quiet_cfg(**cfg), data, num_envs=2)
        env.termination_threshold = math.inf
        edit(env)
        hold = lambda obs: (torch.zeros(obs.shape[0], env.action_dim), None, None)  # noqa: E731
        records = rollout(env, hold, episodes_per_env=1, num_keyframes=data.num_keyframes)
        return [episode_metrics(r) for r in records]

    def lean(x):
        return lambda env: env.ref_gravity_xy.copy_(torch.tensor([x, 0.0]).expand_as(env.ref_gravity_xy))

    def lift(env):
        env.ref_root_pos[:, 2] += 1.0

    assert [e.ending for e in ending(lean(-0.9))] == ["forward"] * 2
    backward = ending(lean(0.9))
    assert [e.ending for e in backward] == ["backward"] * 2 and all(e.ended_by == ("tilt",) for e in backward)
    sank = ending(lift, terminations={"min_base_height": 2.0})  # the height check then follows the reference
    assert [e.ending for e in sank] == ["sank"] * 2 and all(e.ended_by == ("base_height",) for e in sank)
    stood = ending(lambda env: None)
    assert [e.ending for e in stood] == ["completed"] * 2
    assert endings(stood + sank)["ending"]["sank"] == 50.0
