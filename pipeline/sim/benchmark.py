"""Micro-benchmarks of the physics alone: the denominator of benchmarks/env_throughput.py.

`raw_rollout_steps_per_s` is what MuJoCo C itself does with `mujoco.rollout` on the same model,
the same number of worlds and threads, with zero control work: one rollout call of `decimation`
substeps per control step, the last state fed back as the next initial state (one array copy,
which any closed loop needs). Targets hold the home pose, so the robots stand and settle as in
training, not fly apart.
"""

from __future__ import annotations

import time

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout

from pipeline.sim.backend import decimation_for
from pipeline.sim.model import default_state_qpos, sim_model_from


def _home_state_and_ctrl(model: mujoco.MjModel, num_worlds: int, decimation: int):
    data = mujoco.MjData(model)
    data.qpos[:] = default_state_qpos(model)
    mujoco.mj_forward(model, data)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
    row = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, row, spec)
    targets = data.qpos[model.jnt_qposadr[model.actuator_trnid[:, 0]]]
    return np.tile(row, (num_worlds, 1)), np.tile(targets, (num_worlds, decimation, 1))


def raw_rollout_steps_per_s(model, num_worlds: int = 256, *, nthread: int = 2, steps: int = 50,
                            warmup: int = 10, decimation: int | None = None) -> float:
    """Control steps per second summed over worlds (N x steps / s) of bare `mujoco.rollout`."""
    model = sim_model_from(model)
    decimation = decimation_for(model) if decimation is None else decimation
    state0, ctrl = _home_state_and_ctrl(model, num_worlds, decimation)
    states = np.empty((num_worlds, decimation, state0.shape[1]))
    sensors = np.empty((num_worlds, decimation, model.nsensordata))
    models = [model] * num_worlds
    datas = [mujoco.MjData(model) for _ in range(max(1, nthread))]
    with mj_rollout.Rollout(nthread=nthread) as pool:
        for i in range(warmup + steps):
            if i == warmup:
                start = time.perf_counter()
            pool.rollout(models, datas, state0, ctrl, skip_checks=True, nstep=decimation,
                         control_spec=mujoco.mjtState.mjSTATE_CTRL.value, state=states, sensordata=sensors)
            np.copyto(state0, states[:, -1])
        elapsed = time.perf_counter() - start
    return num_worlds * steps / elapsed


def backend_steps_per_s(backend, *, steps: int = 50, warmup: int = 10) -> float:
    """Control steps per second summed over worlds of a backend holding its current targets."""
    from pipeline.sim.model import default_state_qpos as home_of

    model = backend.model
    home = home_of(model)
    n = backend.num_worlds
    backend.set_state(np.arange(n), np.tile(home, (n, 1)), np.zeros((n, model.nv)))
    targets = torch.tensor(home[model.jnt_qposadr[model.actuator_trnid[:, 0]]], dtype=torch.float32)
    ctrl = targets.expand(n, -1).contiguous().to(backend.device)
    for i in range(warmup + steps):
        if i == warmup:
            if backend.device.type == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
        backend.step(ctrl)
    if backend.device.type == "cuda":
        torch.cuda.synchronize()
    return n * steps / (time.perf_counter() - start)


if __name__ == "__main__":
    from pipeline.sim.backend import make_backend
    from pipeline.sim.model import build_sim_model

    sim_model = build_sim_model()
    cpu = make_backend("cpu", sim_model, 256)
    for _ in range(2):  # interleaved, as the machine is shared and its load drifts
        raw = raw_rollout_steps_per_s(sim_model, 256)
        ours = backend_steps_per_s(cpu)
        print(f"raw_steps_per_s={raw:.0f} cpu_backend_steps_per_s={ours:.0f} ratio={ours / raw:.3f}")
