"""ONNX export: parity with torch, metadata inside and beside, sim2sim runs, bad inputs."""

import json

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.common.errors import PipelineInputError
from pipeline.export.metadata import build_metadata, observation_layout
from pipeline.export.onnx_export import DeployedPolicy, export_folder, parity, read_onnx_metadata
from pipeline.export.sim2sim import PsiOutOfRangeWarning, Sim2Sim, load_exported, run_sim2sim
from pipeline.keyframes.tracking_data import TrackingData
from pipeline.motion.motion import RobotKinematics
from pipeline.robot.g1 import default_qpos, load_robot_config


class ComposedStandIn(nn.Module):
    """Same interface as the composed stage-1 + adapters module: normalised obs in,
    (joint action (N, 27), Δφ^Δ (N,)) out."""

    def __init__(self, obs_dim, action_dim=27, phase_rate=0.01):
        super().__init__()
        self.register_buffer("mean", torch.randn(obs_dim) * 0.1)
        self.register_buffer("std", torch.rand(obs_dim) + 0.5)
        self.actor = nn.Sequential(nn.Linear(obs_dim, 64), nn.ELU(), nn.Linear(64, action_dim))
        self.phase = nn.Sequential(nn.Linear(obs_dim, 32), nn.ELU(), nn.Linear(32, 1))
        self.phase_rate = phase_rate

    def forward(self, obs):
        x = ((obs - self.mean) / self.std).clamp(-10, 10)
        a = self.actor(x) * 0.1
        dphi = -0.75 * self.phase_rate + (torch.tanh(self.phase(x)[:, 0]) + 1) * 0.5 * 1.75 * self.phase_rate
        return a + dphi[:, None] * a, dphi


def _tracking_data(task="far_jump", frames=40):
    cfg = load_robot_config()
    kin = RobotKinematics()
    q = default_qpos(cfg)
    root = np.tile(q[:3], (frames, 1))
    root[:, 0] = np.linspace(0, 0.3, frames)
    motion = kin.motion(50.0, root, np.tile(q[3:7], (frames, 1)), np.tile(q[7:], (frames, 1)))
    psi = np.linspace(1.0, 2.0, 11)
    offsets = np.zeros((11, 2, 3))
    offsets[:, 1, 0] = psi - 1.0
    return TrackingData(task=task, motion=motion, keyframe_frames=np.array([10, 30]),
                        keyframe_labels=("", "landing"), sparse_scale=np.array([1.0, 50.0]),
                        edited=np.array([False, True]), psi=psi, keyframe_offsets=offsets, psi_raw=1.0,
                        psi_ranges={"easy": [(1.0, 1.5)], "hard": [(1.5, 2.0)]})


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.manual_seed(0)
    cfg = load_robot_config()
    data = _tracking_data()
    layout = observation_layout(cfg, history=5)
    module = DeployedPolicy(ComposedStandIn(layout["dim"]), cfg.default_joint_pos, cfg.action_scale)
    meta = build_metadata(task="far_jump", variant="adamimic", robot=cfg, data=data, obs_layout=layout)
    out = tmp_path_factory.mktemp("export") / "export"
    result = export_folder(module, layout["dim"], meta, out)
    return module, layout, meta, result


def test_parity_and_metadata(exported):
    module, layout, meta, result = exported
    assert result.parity_max_abs_diff < 1e-5
    assert parity(module, result.onnx, layout["dim"], num=64, seed=3) < 1e-5
    inside = read_onnx_metadata(result.onnx)
    beside = json.loads(result.metadata.read_text())
    for key in ("joint_names", "kp", "kd", "default_joint_pos", "action_scale", "observation",
                "control_rate_hz", "keyframes", "psi_ranges", "robot", "task"):
        assert inside[key] == beside[key], key
    assert beside["joint_names"] == list(load_robot_config().joint_names)
    assert beside["observation"]["dim"] == 5 * (3 + 3 + 27 * 3 + 1 + 1 + 3)
    # keyframe offsets on the grid interpolate the samples: second keyframe x-offset = ψ - 1
    grid = np.array(beside["keyframes"]["psi_grid"])
    np.testing.assert_allclose(np.array(beside["keyframes"]["offsets"])[:, 1, 0], grid - 1.0, atol=1e-12)


def test_sim2sim_runs_a_few_steps(exported):
    _, _, _, result = exported
    runner = Sim2Sim(result.folder, task="far_jump", robot="unitree_g1")
    episode = runner.run_episode(1.2, max_steps=5)
    assert episode.steps == 5 or episode.end in ("tilt", "height")
    assert len(episode.phase) == episode.steps
    assert np.all(np.diff([0.0] + episode.phase) >= 0.25 * runner.phase_rate - 1e-12)
    summary = run_sim2sim(result.folder, [1.1], max_steps=3)
    assert summary["task"] == "far_jump" and len(summary["episodes"]) == 1


def test_bad_inputs(exported, tmp_path):
    _, _, _, result = exported
    with pytest.raises(PipelineInputError, match="task"):
        load_exported(result.folder, task="tennis_hit")
    with pytest.raises(PipelineInputError, match="robot"):
        load_exported(result.folder, robot="h1")
    with pytest.raises(PipelineInputError, match="ONNX policy file not found"):
        (tmp_path / "policy.json").write_text(result.metadata.read_text())
        load_exported(tmp_path)
    with pytest.warns(PsiOutOfRangeWarning):
        Sim2Sim(result.folder).run_episode(3.5, max_steps=1)


def test_play_writes_an_mp4(exported, tmp_path):
    import av

    from pipeline.export.play import play_to_mp4

    _, _, _, result = exported
    out = play_to_mp4(result.folder, psi=1.3, out=tmp_path / "play.mp4", seconds=0.2, width=320, height=240)
    with av.open(str(out)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 5 and frames[0].shape == (240, 320, 3)
    assert frames[0].std() > 5  # a real picture, not a blank frame


def test_export_variant_from_a_real_policy_folder(tmp_path):
    from pipeline.envs.config import EnvConfig
    from pipeline.export.onnx_export import export_variant
    from pipeline.rl.checkpoint import save_policy
    from pipeline.rl.networks import DoubleCritic, Stage1Policy
    from pipeline.rl.stage2 import Stage2Policy

    torch.manual_seed(1)
    cfg = load_robot_config()
    base = Stage1Policy(460, 27, [32], phase_rate=0.02)
    base.normalizer.update(torch.randn(64, 460) * 3)  # non-trivial normalisation inside the graph
    policy = Stage2Policy(base, [16], phase_rate=0.02)
    policy.normalizer.update(torch.randn(64, 460))
    meta = {"robot": cfg.name, "task": "far_jump", "variant": "adamimic", "stage": 2,
            "joint_names": list(cfg.joint_names), "action_dim": 27, "actor_obs_dim": 460, "critic_obs_dim": 492,
            "phase_rate": 0.02, "architecture": {"actor_hidden": [32], "critic_hidden": [16], "adapter_hidden": [16],
                                                 "activation": "elu", "freeze_base": True, "normalize_obs": True}}
    save_policy(tmp_path / "final", policy, DoubleCritic(492, [16]), meta)
    data = _tracking_data()
    result = export_variant(task="far_jump", variant="adamimic", data=data, policy_dir=tmp_path / "final",
                            out_dir=tmp_path / "export", env_cfg=EnvConfig())
    assert result.parity_max_abs_diff < 1e-5
    assert sorted(p.name for p in result.folder.iterdir()) == ["config.json", "model.safetensors",
                                                               "policy.json", "policy.onnx"]
    assert Sim2Sim(result.folder).run_episode(1.4, max_steps=3).steps >= 1
    with pytest.raises(PipelineInputError, match="task"):
        export_variant(task="tennis_hit", variant="adamimic", data=data, policy_dir=tmp_path / "final",
                       out_dir=tmp_path / "export2")
    with pytest.raises(PipelineInputError, match="not found"):
        export_variant(task="far_jump", variant="adamimic", data=data, policy_dir=tmp_path / "missing",
                       out_dir=tmp_path / "export3")
