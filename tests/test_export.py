"""ONNX export: parity with torch, metadata inside and beside, sim2sim runs, bad inputs."""

import json

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.common.errors import PipelineInputError
from pipeline.export.metadata import build_metadata, observation_layout
from pipeline.export.onnx_export import DeployedPolicy, export_folder, parity, read_onnx_metadata
from pipeline.export.sim2sim import PsiOutOfRangeWarning, Sim2Sim, build_scene, load_exported, run_sim2sim
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


def _tracking_data(task="far_jump", frames=40, wave=0.0):
    cfg = load_robot_config()
    kin = RobotKinematics()
    q = default_qpos(cfg)
    root = np.tile(q[:3], (frames, 1))
    root[:, 0] = np.linspace(0, 0.3, frames)
    joints = np.tile(q[7:], (frames, 1))
    joints += wave * np.sin(np.linspace(0, 2 * np.pi, frames))[:, None]  # every joint, so frames differ
    motion = kin.motion(50.0, root, np.tile(q[3:7], (frames, 1)), joints)
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



class LargeOutputs(nn.Module):
    """A stand-in whose raw actions reach the hundreds on the parity check's inputs, as a trained balance
    policy's do (156 measured): float32 rounds those to about 1e-4 absolute."""

    def __init__(self, obs_dim, action_dim=27, gain=300.0):
        super().__init__()
        self.actor = nn.Sequential(nn.Linear(obs_dim, 256), nn.ELU(), nn.Linear(256, action_dim))
        self.gain = gain

    def forward(self, obs):
        return self.gain * self.actor(obs), torch.zeros(obs.shape[0])


def test_parity_scales_with_the_output_and_still_refuses_a_different_graph(exported, tmp_path, monkeypatch):
    import pipeline.export.onnx_export as onnx_export

    module, layout, meta, _ = exported
    cfg = load_robot_config()
    torch.manual_seed(0)
    large = DeployedPolicy(LargeOutputs(layout["dim"]), cfg.default_joint_pos, cfg.action_scale)
    result = export_folder(large, layout["dim"], meta, tmp_path / "large")
    assert parity(large, result.onnx, layout["dim"], scaled=True) < 1e-5 < result.parity_max_abs_diff
    # the graph of another network: refused at any output size, and nothing is written
    real = onnx_export.export_onnx
    monkeypatch.setattr(onnx_export, "export_onnx", lambda m, *a, **k: real(module, *a, **k))
    with pytest.raises(RuntimeError, match="ONNX parity failed"):
        export_folder(large, layout["dim"], meta, tmp_path / "wrong")
    assert not (tmp_path / "wrong").exists()


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
    written = json.loads(result.metadata.read_text())
    assert written["physics"] == "baseline" and written["sim_dt"] == cfg.physics("baseline").timestep
    fast = export_variant(task="far_jump", variant="adamimic", data=data, policy_dir=tmp_path / "final",
                          out_dir=tmp_path / "export_fast", env_cfg=EnvConfig(physics="fast"))
    fast_meta = json.loads(fast.metadata.read_text())
    assert fast_meta["physics"] == "fast" and fast_meta["sim_dt"] == cfg.physics("fast").timestep
    runner = Sim2Sim(fast.folder)  # replays the preset it trained on: its timestep and substeps
    assert runner.decimation == 2  # 10 ms steps in a 20 ms control step
    assert build_scene(fast_meta, 1.4).opt.timestep == cfg.physics("fast").timestep
    with pytest.raises(PipelineInputError, match="policy.json: physics: unknown physics preset 'warp9'"):
        build_scene({**fast_meta, "physics": "warp9"}, 1.4)
    term = written["terminations"]
    assert term["relative_to_reference"] and term["base_height_applies"] and term["base_height_margin"] == 0.25
    with pytest.raises(PipelineInputError, match="task"):
        export_variant(task="tennis_hit", variant="adamimic", data=data, policy_dir=tmp_path / "final",
                       out_dir=tmp_path / "export2")
    with pytest.raises(PipelineInputError, match="not found"):
        export_variant(task="far_jump", variant="adamimic", data=data, policy_dir=tmp_path / "missing",
                       out_dir=tmp_path / "export3")
    from pipeline.priors.push_prior import PushPrior

    with_prior = _tracking_data()  # a task with a push prior, a policy saved without one
    with_prior.push_prior = PushPrior(np.zeros((with_prior.motion.num_frames, 27)), np.array([1.0]), np.array([0.0]),
                                      tuple(cfg.joint_names))
    with pytest.raises(PipelineInputError, match="final: push_prior: checkpoint has false, this run needs true"):
        export_variant(task="far_jump", variant="adamimic", data=with_prior, policy_dir=tmp_path / "final",
                       out_dir=tmp_path / "export4")


@pytest.mark.parametrize("offset, push", [("reference", False), ("feedforward", False), ("feedforward", True)])
def test_reference_action_offset_in_the_graph_matches_the_env(tmp_path, monkeypatch, offset, push):
    """A policy trained with `env.action_offset: reference` or `feedforward` (with or without a push
    prior): the exported graph adds that offset's per-frame joint targets at the frame the env's step
    ends on (adaptive phase included), and the push prior's w(ψ) · push at the observed ψ — same
    targets as the env."""
    from pipeline.envs.config import EnvConfig
    from pipeline.envs.feedforward import zero_action_targets
    from pipeline.envs.tracking_env import TrackingEnv
    from pipeline.export.onnx_export import OUTPUT_NAMES, ReferenceOffset, onnx_session
    from pipeline.priors.push_prior import PushPrior

    torch.manual_seed(2)
    cfg = load_robot_config()
    data = _tracking_data(wave=0.2)
    prior = None
    if push:  # anchors inside the samples' ψ, so worlds sit below, between and above them
        t, j = data.motion.num_frames, len(cfg.joint_names)
        table = 0.3 * np.sin(np.arange(t)[:, None] / 5.0 + np.arange(j)[None])
        lo, hi = float(data.psi.min()), float(data.psi.max())
        anchors = np.array([lo + 0.2 * (hi - lo), lo + 0.5 * (hi - lo), lo + 0.7 * (hi - lo)])
        prior = data.push_prior = PushPrior(table, anchors, np.array([0.1, 0.4, 1.1]), tuple(cfg.joint_names))
    env = TrackingEnv(EnvConfig.from_dict({"randomization": {"enabled": False}, "rsi_prob": 0.0,  # worlds at several ψ:
                                           "action_offset": offset, "sampling": {"mode": "uniform"}}), data, num_envs=4)
    layout = observation_layout(cfg, history=5)
    assert layout["dim"] == env.actor_obs_dim
    table = zero_action_targets(data.motion, offset, cfg)
    reference = ReferenceOffset.for_layout(table, env.dphi, layout, prior)
    module = DeployedPolicy(ComposedStandIn(layout["dim"], phase_rate=env.dphi), cfg.default_joint_pos,
                            cfg.action_scale, reference=reference)
    meta = build_metadata(task="far_jump", variant="adamimic", robot=cfg, data=data, obs_layout=layout,
                          action_offset=offset)
    assert meta["action_offset"] == offset and meta["outputs"]["joint_targets"].startswith("reference.joint_target")
    assert ("push_prior" in meta["reference"]) == push and ("push_prior" in meta["outputs"]["joint_targets"]) == push
    assert np.allclose(meta["reference"]["joint_target"], table) and np.allclose(meta["reference"]["joint_pos"], data.motion.joint_pos)
    assert (offset == "reference") == np.allclose(table, data.motion.joint_pos)
    result = export_folder(module, layout["dim"], meta, tmp_path / "export")
    session = onnx_session(result.onnx)
    sent = []
    delayed = env._delayed_control
    monkeypatch.setattr(env, "_delayed_control", lambda t: sent.append(t.clone()) or delayed(t))
    obs = env.reset()
    for _ in range(12):
        raw = obs["actor"].numpy()
        targets, action, dphi = session.run(list(OUTPUT_NAMES), {"obs": raw})
        obs, *_ = env.step(torch.from_numpy(action), torch.from_numpy(dphi[:, 0]))
        np.testing.assert_allclose(targets, sent[-1].numpy(), atol=1e-5)
    assert np.ptp(env.frame.numpy()) > 0  # the adaptive phase moved the worlds to different frames
    if push:  # the worlds track samples with different pushes
        weights = env.push_weight[env.sample].numpy()
        assert np.ptp(weights) > 0 and np.allclose(weights, prior.weight(env.psi[env.sample].numpy()))


# ------------------------------------------------------------------------------ fall checks
CROUCH_HEIGHT, CROUCH_TILT, FALL_FRAMES = 0.35, 0.85, 40


def _pitch(sin_angle):  # wxyz about y: projected gravity xy = (sin, 0)
    half = 0.5 * np.arcsin(sin_angle)
    return np.array([np.cos(half), 0.0, np.sin(half), 0.0])


def _roll(sin_angle):  # wxyz about x: projected gravity xy = (0, -sin)
    half = 0.5 * np.arcsin(sin_angle)
    return np.array([np.cos(half), np.sin(half), 0.0, 0.0])


def _crouch_data():
    """Stands (frames 0-14), crouches pitched forward to 0.35 m (15-29; both below the absolute
    thresholds: |g_xy| = 0.85 > 0.8, z < 0.4), stands again; the ψ edit lifts the pelvis by
    0.2·(ψ − 1) from the first keyframe (frame 10) on."""
    cfg, kin = load_robot_config(), RobotKinematics()
    q = default_qpos(cfg)
    root, quat = np.tile(q[:3], (FALL_FRAMES, 1)), np.tile(q[3:7], (FALL_FRAMES, 1))
    root[15:30, 2] = CROUCH_HEIGHT
    quat[15:30] = _pitch(CROUCH_TILT)
    motion = kin.motion(50.0, root, quat, np.tile(q[7:], (FALL_FRAMES, 1)))
    psi = np.linspace(1.0, 2.0, 11)
    offsets = np.zeros((11, 2, 3))
    offsets[:, 0, 2] = 0.2 * (psi - 1.0)
    offsets[:, 1, 2] = 0.1 * (psi - 1.0)
    return TrackingData(task="far_jump", motion=motion, keyframe_frames=np.array([10, 30]),
                        keyframe_labels=("crouch", "landing"), sparse_scale=np.array([1.0, 50.0]),
                        edited=np.array([True, True]), psi=psi, keyframe_offsets=offsets, psi_raw=1.0,
                        psi_ranges={"easy": [(1.0, 1.5)], "hard": [(1.5, 2.0)]})


# (frame, ψ-sample, pelvis z, pelvis quaternion, decision of the relative checks)
FALL_CASES = [
    (20, 0, CROUCH_HEIGHT, _pitch(CROUCH_TILT), None),  # following the crouch: absolute would end it
    (20, 0, 0.05, _roll(1.0), "tilt"),  # lying on its side in the crouch: a real fall
    (5, 0, 0.10, _pitch(1.0), "tilt"),  # lying face down while the reference stands
    (5, 0, 0.30, _pitch(0.3), "height"),  # sunk while the reference stands
    (20, 0, CROUCH_HEIGHT, _pitch(0.0), "tilt"),  # upright where the reference leans 0.85
    (20, 10, 0.20, _pitch(CROUCH_TILT), "height"),  # ψ = 2 lifts the crouch to 0.55 m: 0.2 is a fall ...
    (20, 0, 0.20, _pitch(CROUCH_TILT), None),  # ... but not at ψ = 1 (limit 0.35 − 0.25)
    (35, 10, 0.60, _pitch(0.2), None),  # standing again, a little low and leaning
    (14, 0, CROUCH_HEIGHT, _pitch(CROUCH_TILT), "tilt"),  # the crouch one frame early ...
    (15, 0, CROUCH_HEIGHT, _pitch(CROUCH_TILT), None),  # ... and on time: the frame matters
]


def _env_decisions(env_cfg, data, cases):
    """The env's fall decisions ('tilt' before 'height', as sim2sim reports) for hand-made states:
    its physics step is skipped, so it judges exactly the pose it was given at the wanted frame."""
    from pipeline.envs.tracking_env import TrackingEnv

    n = len(cases)
    env = TrackingEnv(env_cfg, data, num_envs=n)
    env.reset()
    env.termination_threshold = float("inf")  # falls only, like the evaluation
    qpos = env.backend.qpos.clone()
    for i, (_, _, z, quat, _) in enumerate(cases):
        qpos[i, 2], qpos[i, 3:7] = z, torch.as_tensor(quat)
    env.backend.set_state(torch.arange(n), qpos, torch.zeros_like(env.backend.qvel))
    env.backend.step = lambda ctrl: None
    frames = torch.tensor([c[0] for c in cases])
    env.sample[:] = torch.tensor([c[1] for c in cases])
    env.phase[:] = frames.to(torch.float64) / (env.num_frames - 1) - env.dphi  # lands on `frames`
    _, _, terminated, _, info = env.step(torch.zeros(n, env.action_dim))
    assert torch.equal(info["frame"], frames)
    by = info["terminated_by"]
    assert torch.equal(terminated, by["tilt"] | by["base_height"])
    return [("tilt" if t else "height" if h else None) for t, h in zip(by["tilt"].tolist(), by["base_height"].tolist())]


def _sim2sim_decisions(env_cfg, data, cases):
    from pipeline.export.metadata import termination_metadata
    from pipeline.export.sim2sim import FallCheck, reference_frame

    cfg = load_robot_config()
    meta = build_metadata(task=data.task, variant="adamimic", robot=cfg, data=data,
                          obs_layout=observation_layout(cfg), terminations=termination_metadata(env_cfg.terminations, data.task))
    meta = json.loads(json.dumps(meta))  # what sim2sim reads from policy.json
    t = meta["phase"]["num_frames"]
    out = []
    for frame, sample, z, quat, _ in cases:
        w, x, y, _z = quat
        gravity = np.array([2 * (w * y - x * _z), -2 * (y * _z + w * x), -1.0])
        phase = frame / (t - 1)
        assert reference_frame(phase, t) == frame
        out.append(FallCheck.from_metadata(meta, float(data.psi[sample]))(gravity, z, reference_frame(phase, t)))
    return out


def test_sim2sim_fall_check_matches_the_env():
    from pipeline.envs.config import EnvConfig

    data = _crouch_data()
    env_cfg = EnvConfig.from_dict({"randomization": {"enabled": False}, "rsi_prob": 0.0})
    assert env_cfg.terminations.relative_to_reference  # the default being mirrored
    expected = [c[-1] for c in FALL_CASES]
    assert _sim2sim_decisions(env_cfg, data, FALL_CASES) == expected
    assert _env_decisions(env_cfg, data, FALL_CASES) == expected
    # the absolute checks (the old sim2sim) end the closely followed crouch at once
    absolute = EnvConfig.from_dict({"randomization": {"enabled": False}, "rsi_prob": 0.0,
                                    "terminations": {"relative_to_reference": False}})
    assert _sim2sim_decisions(absolute, data, FALL_CASES[:1]) == ["tilt"]
    assert _sim2sim_decisions(absolute, data, FALL_CASES) == _env_decisions(absolute, data, FALL_CASES)
    # a task exempt from the height check: neither checks height
    exempt = EnvConfig.from_dict({"randomization": {"enabled": False}, "rsi_prob": 0.0,
                                  "terminations": {"base_height_exempt_tasks": ["far_jump"]}})
    assert "height" not in _sim2sim_decisions(exempt, data, FALL_CASES)
    assert _sim2sim_decisions(exempt, data, FALL_CASES) == _env_decisions(exempt, data, FALL_CASES)


def test_reference_metadata_per_frame():
    from pipeline.export.metadata import reference_metadata

    data = _crouch_data()
    grid = np.linspace(1.0, 2.0, 41)
    ref = json.loads(json.dumps(reference_metadata(data, grid)))
    assert ref["num_frames"] == FALL_FRAMES
    np.testing.assert_allclose(ref["root_height"], data.motion.root_pos[:, 2])
    g = np.array(ref["projected_gravity_xy"])
    np.testing.assert_allclose(g[20], [CROUCH_TILT, 0.0], atol=1e-9)
    np.testing.assert_allclose(g[5], [0.0, 0.0], atol=1e-9)
    dz = np.array(ref["root_height_offset"])  # (G, T): the latest keyframe's z edit at each frame
    assert dz.shape == (41, FALL_FRAMES)
    np.testing.assert_allclose(dz[:, :10], 0.0)
    np.testing.assert_allclose(dz[:, 10:30], np.repeat(0.2 * (grid - 1.0)[:, None], 20, 1), atol=1e-12)
    np.testing.assert_allclose(dz[:, 30:], np.repeat(0.1 * (grid - 1.0)[:, None], 10, 1), atol=1e-12)


def test_sim2sim_phase_to_frame_is_the_envs():
    from pipeline.export.sim2sim import reference_frame

    t = FALL_FRAMES
    phases = np.concatenate([np.linspace(-0.1, 1.1, 997), (np.arange(t) + 0.5) / (t - 1)])  # incl. halves
    env_frames = (torch.as_tensor(phases) * (t - 1)).round().long().clamp(0, t - 1)
    assert [reference_frame(p, t) for p in phases] == env_frames.tolist()
