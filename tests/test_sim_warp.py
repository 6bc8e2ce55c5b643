"""WarpBackend: equivalence with the CPU backend (both on CPU), per-world fields, GPU checks.

Why CPU and Warp trajectories can differ at all: Warp computes in float32 (MuJoCo C in float64),
its constraint solver runs a fixed iteration budget with its own line search and no warm start
carried across rollout calls on the C side, and its collision code generates contacts with its own
primitives (capsule-plane/box here). Measured here over 15 control steps with feet landing:
worst qpos difference ~4e-6, site positions ~4e-7 m, contact flags identical. The tolerances
(1e-4) leave a 25x margin; over long horizons the two would drift apart (contact is chaotic).

The first run compiles mujoco_warp's kernels for the CPU (~40 s, then cached by Warp).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("mujoco_warp")

from pipeline.sim.backend import make_backend  # noqa: E402
from pipeline.sim.model import build_sim_model, default_state_qpos  # noqa: E402

QPOS_TOL = 1e-4       # rad or m, after 15 control steps with contacts
SITE_TOL = 1e-4       # m
STEPS = 15
NUM_WORLDS = 3


@pytest.fixture(scope="module")
def model():
    return build_sim_model()


@pytest.fixture(scope="module")
def warp_cpu(model):
    return make_backend("warp", model, NUM_WORLDS, device="cpu", allow_warp_on_cpu=True)


def _start_states(model, rng):
    home = default_state_qpos(model)
    qpos = np.tile(home, (NUM_WORLDS, 1))
    qpos[1, 2] += 0.03                              # drops onto its feet
    qpos[2, 7:] += rng.uniform(-0.1, 0.1, model.nq - 7)  # a perturbed pose
    qvel = np.zeros((NUM_WORLDS, model.nv))
    qvel[2] = rng.normal(0.0, 0.05, model.nv)
    return qpos, qvel


def test_cpu_and_warp_trajectories_agree(model, warp_cpu):
    _check_cpu_and_warp_agree(model, warp_cpu)


def test_cpu_and_warp_agree_on_the_fast_physics_preset():
    """Both backends take the same compiled model, so a physics preset (robots/g1/robot.yaml) reaches both:
    10 ms substeps, two per control step, three capsules per foot."""
    fast = build_sim_model(physics="fast")
    warp = make_backend("warp", fast, NUM_WORLDS, device="cpu", allow_warp_on_cpu=True)
    assert warp.decimation == 2 and warp.model.opt.timestep == 0.01
    _check_cpu_and_warp_agree(fast, warp)
    warp.close()


def _check_cpu_and_warp_agree(model, warp_cpu):
    rng = np.random.default_rng(3)
    cpu = make_backend("cpu", model, NUM_WORLDS)
    qpos, qvel = _start_states(model, rng)
    for backend in (cpu, warp_cpu):
        backend.set_state(np.arange(NUM_WORLDS), qpos, qvel)
    np.testing.assert_allclose(warp_cpu.site_pos.numpy(), cpu.site_pos.numpy(), atol=1e-5)

    targets = qpos[:, model.jnt_qposadr[model.actuator_trnid[:, 0]]]
    worst_qpos = worst_site = 0.0
    contact_agree = []
    for step in range(STEPS):
        noise = rng.normal(0.0, 0.05, (NUM_WORLDS, cpu.decimation, model.nu))
        ctrl = torch.tensor(targets[:, None, :] + noise, dtype=torch.float32)  # per-substep targets
        cpu.step(ctrl)
        warp_cpu.step(ctrl)
        worst_qpos = max(worst_qpos, (cpu.qpos - warp_cpu.qpos).abs().max().item())
        worst_site = max(worst_site, (cpu.site_pos - warp_cpu.site_pos).abs().max().item())
        contact_agree.append((cpu.foot_contact == warp_cpu.foot_contact).float().mean().item())
    print(f"worst qpos diff {worst_qpos:.2e}, site diff {worst_site:.2e}, contact agreement {np.mean(contact_agree):.2f}")
    assert worst_qpos < QPOS_TOL, worst_qpos
    assert worst_site < SITE_TOL, worst_site
    assert np.mean(contact_agree) > 0.9
    assert cpu.foot_contact.any()  # the comparison did include contact
    force_scale = cpu.actuator_force.abs().max().item()
    assert (cpu.actuator_force - warp_cpu.actuator_force).abs().max().item() < 0.05 * force_scale + 0.5


def test_warp_views_and_per_world_fields(model, warp_cpu):
    n = NUM_WORLDS
    assert warp_cpu.qpos.shape == (n, model.nq) and warp_cpu.qpos.dtype == torch.float32
    assert warp_cpu.site_quat.shape == (n, 17, 4) and warp_cpu.foot_contact.dtype == torch.bool
    torso = model.body("torso_link").id
    mass = warp_cpu.get_model_field("body_mass", [1])
    mass[0, torso] += 5.0
    warp_cpu.set_model_field("body_mass", [1], mass)
    got = warp_cpu.get_model_field("body_mass", [0, 1, 2])[:, torso]
    assert got[1] == pytest.approx(model.body_mass[torso] + 5.0, rel=1e-6)
    assert got[0] == pytest.approx(model.body_mass[torso]) and got[2] == pytest.approx(model.body_mass[torso])
    # a field outside PER_WORLD_FIELDS is expanded on first write
    damping = warp_cpu.get_model_field("dof_damping", [2])
    warp_cpu.set_model_field("dof_damping", [2], damping + 1.0)
    assert warp_cpu.get_model_field("dof_damping", [2])[0, 6] == pytest.approx(damping[0, 6] + 1.0)
    assert warp_cpu.get_model_field("dof_damping", [0])[0, 6] == pytest.approx(damping[0, 6])

    start = default_state_qpos(model)
    start[2] += 1.0
    warp_cpu.set_state(np.arange(n), np.tile(start, (n, 1)), np.zeros((n, model.nv)))
    targets = torch.tensor(start[model.jnt_qposadr[model.actuator_trnid[:, 0]]] + 0.3, dtype=torch.float32)
    for _ in range(3):
        warp_cpu.step(targets.expand(n, -1))
    assert (warp_cpu.qpos[1] - warp_cpu.qpos[0]).abs().max() > 1e-4


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_warp_on_gpu_steps_with_graph_and_matches_cpu(model):
    n = 64
    gpu = make_backend("warp", model, n)
    cpu = make_backend("cpu", model, n)
    assert gpu.qpos.device.type == "cuda" and gpu._use_graph
    home = default_state_qpos(model)
    for backend in (gpu, cpu):
        backend.set_state(np.arange(n), np.tile(home, (n, 1)), np.zeros((n, model.nv)))
    targets = torch.tensor(home[model.jnt_qposadr[model.actuator_trnid[:, 0]]], dtype=torch.float32)
    for _ in range(10):  # the first step records the CUDA graph, the others replay it
        gpu.step(targets.expand(n, -1).cuda())
        cpu.step(targets.expand(n, -1))
    torch.cuda.synchronize()
    assert (gpu.qpos.cpu() - cpu.qpos).abs().max().item() < QPOS_TOL
    assert gpu.foot_contact.device.type == "cuda"
    assert not gpu.contact_overflow()
