"""TrackingEnv on the MuJoCo Warp backend: the GPU profile's environment, run on CPU here.

test_sim_warp.py checks the backends alone. This checks what only the environment does to one: domain
randomisation and the gap terrain written per world through `set_model_field`, reference-state starts
through `set_state`, and resets of ended worlds in the middle of a run. Same seed, same clip: the two
backends must start from the same states and models and stay together.

How far apart they may drift: Warp computes in float32. A reference pose with a foot exactly on the
floor (the retargeting snaps feet to it) is 1e-8 m above it in float64 and 1e-7 m below it in
float32, so Warp's foot touches one substep (5 ms) earlier than MuJoCo C's; measured here, that moves
an ankle by about 2e-3 rad, and the two then settle together. The tolerances below allow for that.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("mujoco_warp")

import pipeline.sim.backend as backend_module  # noqa: E402
from pipeline.envs.config import EnvConfig  # noqa: E402
from pipeline.envs.tracking_env import TrackingEnv  # noqa: E402
from pipeline.common.yaml_strict import load_yaml_strict  # noqa: E402
from pipeline.keyframes.task_parsing import load_tasks  # noqa: E402
from pipeline.keyframes.edit import build_tracking_data  # noqa: E402
from pipeline.keyframes.select import select_keyframes  # noqa: E402
from pipeline.keyframes.synthetic import Flight, synthetic_jump_motion  # noqa: E402

N = 4
STEPS = 12
ROOT_TOL = 0.01  # m, pelvis position after STEPS control steps


def _far_jump_data(num_samples: int):
    """D_edit of a synthetic 1 m far jump under the paper's far-jump task (gap terrain)."""
    tasks = load_tasks(load_yaml_strict(Path(__file__).resolve().parents[1] / "pipeline/keyframes/paper_tasks.yaml")["tasks"])
    motion = synthetic_jump_motion([Flight(1.0, 0.4, 1.1)], duration=2.0)
    task = tasks["far_jump"]
    return build_tracking_data(motion, task, select_keyframes(motion, task), "edit", num_samples)


@pytest.fixture(scope="module")
def far_jump():
    return _far_jump_data(8)


@pytest.fixture
def warp_allowed_on_cpu(monkeypatch):
    monkeypatch.setattr(backend_module, "make_backend",
                        functools.partial(backend_module.make_backend, allow_warp_on_cpu=True))


def _pair(data, cfg):
    envs = {}
    for name in ("cpu", "warp"):
        torch.manual_seed(0)  # the env draws ψ, starts and randomisation from torch's global RNG
        env = TrackingEnv(cfg, data, num_envs=N, backend=name, device="cpu")
        envs[name] = (env, env.reset())
    return envs["cpu"], envs["warp"]


def _assert_same_models(cpu, warp, ids):
    """Every MjModel field the env writes per world (randomisation and terrain) reached Warp's worlds."""
    for field in cpu._model_fields():
        a = np.asarray(cpu.backend.get_model_field(field, ids), dtype=np.float64)
        b = np.asarray(warp.backend.get_model_field(field, ids), dtype=np.float64)
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6, err_msg=field)


def _step_both(cpu, warp, actions):
    outs = []
    for env in (cpu, warp):
        torch.manual_seed(1)  # odometry noise and pushes draw in step
        outs.append([env.step(a) for a in actions][-1])
    return outs


def test_randomised_worlds_on_a_gap_start_and_move_together(far_jump, warp_allowed_on_cpu):
    cfg = EnvConfig.from_dict({"sampling": {"mode": "uniform"}})  # several ψ, so several terrains
    (cpu, obs_cpu), (warp, obs_warp) = _pair(far_jump, cfg)
    assert warp.backend.__class__.__name__ == "WarpBackend"
    assert len(set(cpu.sample.tolist())) > 1, "the worlds should track different ψ samples"
    ids = np.arange(N)
    assert {"body_mass", "geom_friction", "actuator_gainprm", "geom_pos"} <= set(cpu._model_fields())
    _assert_same_models(cpu, warp, ids)
    # randomisation and terrain did reach the worlds: they differ from one another
    assert not np.allclose(cpu.backend.get_model_field("body_mass", ids)[0], cpu.backend.get_model_field("body_mass", ids)[1])
    assert not np.allclose(cpu.backend.get_model_field("geom_pos", ids)[0], cpu.backend.get_model_field("geom_pos", ids)[1])
    torch.testing.assert_close(warp.backend.qpos, cpu.backend.qpos, atol=1e-5, rtol=0)
    torch.testing.assert_close(obs_warp["actor"], obs_cpu["actor"], atol=1e-4, rtol=0)

    torch.manual_seed(2)
    actions = [0.1 * torch.randn(N, cpu.action_dim) for _ in range(STEPS)]
    (o_c, _, term_c, trunc_c, _), (o_w, _, term_w, trunc_w, _) = _step_both(cpu, warp, actions)
    assert torch.isfinite(o_w["actor"]).all() and torch.isfinite(o_w["critic"]).all()
    assert torch.equal(term_c, term_w) and torch.equal(trunc_c, trunc_w)
    root_gap = (warp.backend.qpos[:, :3] - cpu.backend.qpos[:, :3]).abs().max().item()
    assert root_gap < ROOT_TOL, root_gap
    torch.testing.assert_close(warp.phase, cpu.phase)


def test_an_ended_world_restarts_the_same_on_both(far_jump, warp_allowed_on_cpu):
    cfg = EnvConfig.from_dict({"sampling": {"mode": "uniform"}, "rsi_prob": 1.0})
    (cpu, _), (warp, _) = _pair(far_jump, cfg)
    for env in (cpu, warp):  # world 0 lies on the floor: it must end and restart on this step
        qpos, qvel = env.backend.qpos[:1].clone(), env.backend.qvel[:1].clone()
        qpos[0, 2] = 0.15
        env.backend.set_state(torch.tensor([0]), qpos, torch.zeros_like(qvel))
    hold = [torch.zeros(N, cpu.action_dim)]
    (_, _, term_c, _, _), (_, _, term_w, _, _) = _step_both(cpu, warp, hold)
    assert bool(term_c[0]) and bool(term_w[0])
    assert int(cpu.episode_step[0]) == int(warp.episode_step[0]) == 0  # restarted
    assert int(cpu.sample[0]) == int(warp.sample[0])
    torch.testing.assert_close(warp.backend.qpos[0], cpu.backend.qpos[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(warp.backend.qvel[0], cpu.backend.qvel[0], atol=1e-4, rtol=0)
    _assert_same_models(cpu, warp, np.array([0]))


needs_gpu = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")]


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=needs_gpu)])
def test_gpu_profile_trains_both_stages_on_the_warp_backend(far_jump, warp_allowed_on_cpu, tmp_path, device):
    """The GPU profile's whole training path (Warp worlds, its networks, PPO, checkpoints, stage 2 on the
    frozen stage 1), shrunk: on CPU, the one run of it that needs no GPU; on a GPU, as trained there."""
    from pipeline.rl.checkpoint import load_policy
    from pipeline.rl.config import TrainConfig
    from pipeline.rl.training import train_stage1, train_stage2

    cfg = TrainConfig.from_dict({"profile": "gpu", "device": device, "iterations_stage1": 2, "iterations_stage2": 1,
                                 "ppo": {"num_envs": N, "steps_per_iteration": 6, "minibatches": 2}})
    assert cfg.backend == "warp" and cfg.network.actor_hidden == [512, 256, 128]
    env_cfg = EnvConfig.from_dict({})
    stage1 = train_stage1(far_jump, env_cfg, cfg, tmp_path / "s1", tensorboard=False, progress=False)
    assert stage1["iterations"] == 2 and stage1["env_steps"] == 2 * N * 6
    history = json.loads((tmp_path / "s1" / "history.json").read_text())
    assert all(np.isfinite(h["policy_loss"]) and np.isfinite(h["value_loss_sparse"]) for h in history)
    stage2 = train_stage2(far_jump, env_cfg, cfg, tmp_path / "s2", stage1_dir=tmp_path / "s1" / "policy",
                          tensorboard=False, progress=False)
    assert stage2["iterations"] == 1
    policy, meta = load_policy(tmp_path / "s2" / "policy")
    assert meta["stage"] == 2 and meta["train_config"]["backend"] == "warp"
    assert all(torch.isfinite(p).all() for p in policy.parameters())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_env_on_the_gpu_moves_like_the_cpu_backend():
    """The gpu profile's training setting: env tensors and Warp worlds on CUDA. The two devices' RNG
    streams differ, so nothing is drawn: one ψ sample, no randomisation, no reference-state starts, no
    odometry noise. Both envs then start alike, on the same gap, and must stay together."""
    data = _far_jump_data(1)
    cfg = EnvConfig.from_dict({"randomization": {"enabled": False}, "rsi_prob": 0.0, "sampling": {"mode": "uniform"},
                               "observations": {"odometry_noise_std": 0.0}})
    gpu = TrackingEnv(cfg, data, num_envs=N, backend="warp", device="cuda")
    cpu = TrackingEnv(cfg, data, num_envs=N, backend="cpu", device="cpu")
    obs_gpu, obs_cpu = gpu.reset(), cpu.reset()
    assert gpu.backend.qpos.device.type == "cuda" and obs_gpu["actor"].device.type == "cuda"
    torch.testing.assert_close(obs_gpu["actor"].cpu(), obs_cpu["actor"], atol=1e-4, rtol=0)
    torch.manual_seed(2)
    actions = [0.1 * torch.randn(N, cpu.action_dim) for _ in range(STEPS)]
    for a in actions:
        o_g, _, term_g, trunc_g, _ = gpu.step(a.cuda())
        o_c, _, term_c, trunc_c, _ = cpu.step(a)
    torch.cuda.synchronize()
    assert torch.isfinite(o_g["actor"]).all()
    assert torch.equal(term_g.cpu(), term_c) and torch.equal(trunc_g.cpu(), trunc_c)
    root_gap = (gpu.backend.qpos[:, :3].cpu() - cpu.backend.qpos[:, :3]).abs().max().item()
    assert root_gap < ROOT_TOL, root_gap
