"""CpuBackend (MuJoCo C + rollout threads) and the backend factory: fast, CPU only."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.robot.g1 import add_flat_ground, build_model, build_spec
from pipeline.sim.backend import make_backend
from pipeline.sim.benchmark import raw_rollout_steps_per_s
from pipeline.sim.model import build_sim_model, default_state_qpos, sensor_layout


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return build_sim_model()


def _targets(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    return qpos[model.jnt_qposadr[model.actuator_trnid[:, 0]]]


def test_views_have_contract_shapes_and_dtypes(model):
    backend = make_backend("cpu", model, 3)
    n, s = 3, len(backend.site_names)
    assert s == 17 and backend.decimation == 4 and (backend.nq, backend.nv, backend.nu) == (34, 33, 27)
    expected = {"qpos": (n, 34), "qvel": (n, 33), "site_pos": (n, s, 3), "site_quat": (n, s, 4),
                "actuator_force": (n, 27)}
    for name, shape in expected.items():
        view = getattr(backend, name)
        assert tuple(view.shape) == shape and view.dtype == torch.float32, name
    assert backend.foot_contact.shape == (n, 2) and backend.foot_contact.dtype == torch.bool
    qpos_view = backend.qpos
    backend.step(torch.tensor(_targets(model, default_state_qpos(model)), dtype=torch.float32).expand(n, -1))
    backend.step(torch.zeros(n, backend.decimation, 27))  # per-substep targets
    assert backend.qpos is qpos_view  # views are refreshed in place
    assert torch.isfinite(backend.qpos).all()
    backend.close()


def test_set_state_reads_back_and_makes_site_poses_current(model):
    backend = make_backend("cpu", model, 4)
    rng = np.random.default_rng(0)
    home = default_state_qpos(model)
    qpos = np.tile(home, (2, 1))
    qpos[:, 0:2] = rng.uniform(-1, 1, (2, 2))
    qpos[:, 7:] += rng.uniform(-0.2, 0.2, (2, model.nq - 7))
    qvel = rng.normal(0, 0.1, (2, model.nv))
    before = backend.qpos[[0, 3]].clone()
    backend.set_state(torch.tensor([1, 2]), torch.tensor(qpos), torch.tensor(qvel))
    np.testing.assert_allclose(backend.qpos[[1, 2]].numpy(), qpos, atol=1e-6)
    np.testing.assert_allclose(backend.qvel[[1, 2]].numpy(), qvel, atol=1e-6)
    assert torch.equal(backend.qpos[[0, 3]], before)  # other worlds untouched

    data = mujoco.MjData(model)
    layout = sensor_layout(model)
    sites = [model.site(name).id for name in layout.site_names]
    for row, world in enumerate((1, 2)):
        data.qpos[:], data.qvel[:] = qpos[row], qvel[row]
        mujoco.mj_forward(model, data)
        np.testing.assert_allclose(backend.site_pos[world].numpy(), data.site_xpos[sites], atol=1e-5)
        quat = np.empty((len(sites), 4))
        for k, sid in enumerate(sites):
            mujoco.mju_mat2Quat(quat[k], data.site_xmat[sid])
        same_sign = np.sign(quat[:, :1]) * np.sign(backend.site_quat[world, :, :1].numpy())
        np.testing.assert_allclose(backend.site_quat[world].numpy() * same_sign, quat, atol=1e-5)
    # pelvis site follows the root position written
    np.testing.assert_allclose(backend.site_pos[[1, 2], 0].numpy(), qpos[:, 0:3], atol=1e-5)


@pytest.mark.parametrize("kind", ["cpu", "warp"])
def test_set_state_without_forward_leaves_the_next_step_unchanged(model, kind):
    """forward=False writes qpos/qvel only (derived views stay stale until the next step): the step
    after it is the step after a full set_state."""
    kwargs = {}
    if kind == "warp":
        pytest.importorskip("mujoco_warp")
        kwargs = {"device": "cpu", "allow_warp_on_cpu": True}
    rng = np.random.default_rng(1)
    home = default_state_qpos(model)
    qpos = np.tile(home, (2, 1))
    qpos[:, 2] += 0.02  # lands on its feet within the steps below
    qpos[:, 7:] += rng.uniform(-0.1, 0.1, (2, model.nq - 7))
    qvel = rng.normal(0, 0.1, (2, model.nv))
    ctrl = torch.tensor(_targets(model, home), dtype=torch.float32).expand(3, -1)
    runs = []
    for forward in (True, False):
        backend = make_backend(kind, model, 3, **kwargs)
        backend.step(ctrl)
        stale_sites = backend.site_pos[1].clone()
        backend.set_state(torch.tensor([1, 2]), torch.tensor(qpos), torch.tensor(qvel), forward=forward)
        np.testing.assert_allclose(backend.qpos[[1, 2]].numpy(), qpos, atol=1e-6)
        np.testing.assert_allclose(backend.qvel[[1, 2]].numpy(), qvel, atol=1e-6)
        assert torch.equal(backend.site_pos[1], stale_sites) != forward
        states = []
        for _ in range(5):
            backend.step(ctrl)
            states.append(torch.cat([backend.qpos.flatten(), backend.site_pos.flatten(), backend.actuator_force.flatten(),
                                     backend.foot_contact.flatten().float()]))
        runs.append(torch.stack(states))
        backend.close()
    assert runs[0][-1, -6:].any()  # feet in contact by the end
    torch.testing.assert_close(runs[1], runs[0], rtol=0.0, atol=1e-6 if kind == "warp" else 0.0)


def test_gravity_fall_matches_single_world_mj_step_exactly(model):
    """No contacts, no active constraints: rollout's worlds must equal a plain mj_step loop bit for bit."""
    n, steps = 3, 10
    backend = make_backend("cpu", model, n)
    start = default_state_qpos(model)
    start[2] += 1.0  # 1 m up: 0.2 s of fall stays clear of the ground
    # float32-representable targets: the views and ctrl are float32, mj_step's reference is float64
    targets = (_targets(model, start) + 0.1).astype(np.float32).astype(np.float64)
    backend.set_state(np.arange(n), np.tile(start, (n, 1)), np.zeros((n, model.nv)))

    data = mujoco.MjData(model)
    data.qpos[:] = start
    data.ctrl[:] = targets
    for _ in range(steps):
        backend.step(torch.tensor(targets, dtype=torch.float32).expand(n, -1))
        for _ in range(backend.decimation):
            mujoco.mj_step(model, data)
        assert data.ncon == 0
        for world in range(n):
            state_row = backend._state0[world]  # the float64 state behind the views
            assert np.array_equal(state_row[1:1 + model.nq], data.qpos)
            assert np.array_equal(state_row[1 + model.nq:1 + model.nq + model.nv], data.qvel)
    assert np.array_equal(backend.qpos.numpy(), np.tile(data.qpos.astype(np.float32), (n, 1)))
    layout = sensor_layout(model)
    sensor_pos = data.sensordata[layout.site_pos[0]:layout.site_pos[1]].reshape(-1, 3)
    assert np.array_equal(backend.site_pos[0].numpy(), sensor_pos.astype(np.float32))
    assert data.qpos[2] < start[2] - 0.15  # it did fall
    assert not backend.foot_contact.any()


def test_per_world_parameters_change_only_chosen_worlds(model):
    n = 3
    backend = make_backend("cpu", model, n)
    start = default_state_qpos(model)
    start[2] += 1.0
    backend.set_state(np.arange(n), np.tile(start, (n, 1)), np.zeros((n, model.nv)))
    torso = model.body("torso_link").id
    masses = backend.get_model_field("body_mass", [0, 1, 2])
    new_mass = masses[1].copy()
    new_mass[torso] += 5.0
    backend.set_model_field("body_mass", [1], new_mass[None])
    assert backend.get_model_field("body_mass", [1])[0, torso] == pytest.approx(masses[1, torso] + 5.0)
    assert backend.get_model_field("body_mass", [0])[0, torso] == masses[0, torso]
    assert model.body_mass[torso] == masses[0, torso]  # base model untouched
    targets = torch.tensor(_targets(model, start) + 0.3, dtype=torch.float32).expand(n, -1)
    for _ in range(5):
        backend.step(targets)
    assert torch.equal(backend.qpos[0], backend.qpos[2])
    assert (backend.qpos[1] - backend.qpos[0]).abs().max() > 1e-4


def _terrain_with_block(spec: mujoco.MjSpec) -> None:
    add_flat_ground(spec)
    spec.worldbody.add_geom(name="block", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[10.0, 0.0, 0.0],
                            size=[0.1, 0.1, 0.1], contype=1, conaffinity=1, condim=3)


def test_resized_terrain_geom_collides_in_its_world_only():
    """Moving and growing a box (terrain per ψ) must also grow its collision bounds."""
    model = build_sim_model(terrain=_terrain_with_block)
    backend = make_backend("cpu", model, 2)
    block = model.geom("block").id
    pos, size = backend.get_model_field("geom_pos", [1]), backend.get_model_field("geom_size", [1])
    pos[0, block], size[0, block] = (0.0, 0.0, 0.0), (1.0, 1.0, 0.2)
    backend.set_model_field("geom_pos", [1], pos)
    backend.set_model_field("geom_size", [1], size)
    assert backend.get_model_field("geom_rbound", [1])[0, block] == pytest.approx(np.linalg.norm([1, 1, 0.2]))
    # the bounds the compiler would give the block at its new place and size
    def moved_block(spec):
        add_flat_ground(spec)
        spec.worldbody.add_geom(name="block", type=mujoco.mjtGeom.mjGEOM_BOX, pos=[0.0, 0.0, 0.0],
                                size=[1.0, 1.0, 0.2], contype=1, conaffinity=1, condim=3)
    compiled = build_sim_model(terrain=moved_block)
    world = backend.world_model(1)
    np.testing.assert_allclose(world.geom_aabb[block], compiled.geom_aabb[block])
    nodes = slice(compiled.body_bvhadr[0], compiled.body_bvhadr[0] + compiled.body_bvhnum[0])
    np.testing.assert_allclose(world.bvh_aabb[nodes], compiled.bvh_aabb[nodes])
    start = default_state_qpos(model)
    start[2] += 0.05  # feet just above the floor, but inside the grown block (top at z = 0.2)
    backend.set_state([0, 1], np.tile(start, (2, 1)), np.zeros((2, model.nv)))
    assert not backend.foot_contact[0].any()
    assert backend.foot_contact[1].all()


def test_model_without_sensors_is_refused_and_spec_is_accepted():
    with pytest.raises(PipelineInputError, match="build_sim_model"):
        make_backend("cpu", build_model(), 2)
    backend = make_backend("cpu", build_spec(visual=False), 2)
    assert backend.site_pos.shape == (2, 17, 3)


@pytest.mark.parametrize("kwargs, field", [
    (dict(name="bogus", num_worlds=2), "name"),
    (dict(name="cpu", num_worlds=0), "num_worlds"),
    (dict(name="cpu", num_worlds=-3), "num_worlds"),
    (dict(name="cpu", num_worlds=2.5), "num_worlds"),
    (dict(name="warp", num_worlds=2, device="cpu"), "device"),
])
def test_factory_rejects_bad_input(model, kwargs, field):
    with pytest.raises(PipelineInputError) as err:
        make_backend(model=model, **kwargs)
    assert err.value.field == field


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error raised without a GPU")
def test_warp_without_gpu_is_a_clear_error(model):
    with pytest.raises(PipelineInputError, match="CUDA"):
        make_backend("warp", model, 2)


def test_bad_step_and_state_input(model):
    backend = make_backend("cpu", model, 2)
    with pytest.raises(PipelineInputError, match="ctrl"):
        backend.step(torch.zeros(3, 27))
    with pytest.raises(PipelineInputError, match="ctrl"):
        backend.step(torch.zeros(2, 3, 27))
    with pytest.raises(PipelineInputError, match="NaN"):
        backend.step(torch.full((2, 27), float("nan")))
    good_q, good_v = np.zeros((1, model.nq)), np.zeros((1, model.nv))
    with pytest.raises(PipelineInputError, match="world_ids"):
        backend.set_state([2], good_q, good_v)
    with pytest.raises(PipelineInputError, match="duplicates"):
        backend.set_state([0, 0], np.zeros((2, model.nq)), np.zeros((2, model.nv)))
    with pytest.raises(PipelineInputError, match="qpos"):
        backend.set_state([0], np.zeros((1, 5)), good_v)
    with pytest.raises(PipelineInputError, match="NaN"):
        backend.set_state([0], np.full((1, model.nq), np.nan), good_v)
    with pytest.raises(PipelineInputError, match="not a numeric MjModel"):
        backend.set_model_field("no_such_field", [0], 1.0)
    with pytest.raises(PipelineInputError, match="broadcast"):
        backend.set_model_field("body_mass", [0], np.ones(3))


def test_raw_rollout_benchmark_helper_runs(model):
    rate = raw_rollout_steps_per_s(model, num_worlds=8, steps=3, warmup=1)
    assert np.isfinite(rate) and rate > 0
