"""CpuBackend: N worlds on MuJoCo C, stepped by `mujoco.rollout` on a persistent thread pool.

One `Rollout.rollout` call per control step runs all worlds for `decimation` substeps on `nthread`
threads with the GIL released. Everything the environment reads comes back in two preallocated
float64 arrays (the per-substep states and sensordata); step() then does a handful of vectorised
copies into the float32 torch views. No Python loop over worlds runs in step().

Per-world parameters: rollout takes one MjModel per world. All worlds share the base model until
`set_model_field` gives a world its own copy (copy on write), so an undisturbed batch costs the
same as raw rollout and memory grows only with the worlds actually randomised.

What differs from stepping one MjData with mj_step in a loop: rollout starts every call with a zero
solver warm start (qacc_warmstart is not part of the state it returns), so with active contacts
the solver's iterates differ at the level of its tolerance across control-step boundaries. Without
constraints (free fall) the trajectories are bit-identical; the test checks that.
"""

from __future__ import annotations

import copy

import mujoco
import numpy as np
import torch
from mujoco import rollout as mj_rollout

from pipeline.common.errors import PipelineInputError
from pipeline.sim.backend import PhysicsBackend
from pipeline.sim.model import default_state_qpos, geom_bounds, refresh_body_bvh

_STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
_CTRL_SPEC = mujoco.mjtState.mjSTATE_CTRL.value
_STATIC_GEOM_FIELDS = ("geom_size", "geom_pos", "geom_quat")


def state_offsets(model: mujoco.MjModel) -> tuple[int, int, int]:
    """(time, qpos, qvel) offsets in an mjSTATE_FULLPHYSICS row (components are stored in bit order)."""
    time_size = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_TIME.value)
    return 0, time_size, time_size + model.nq


class CpuBackend(PhysicsBackend):
    def __init__(self, model, num_worlds: int, *, nthread: int = 2, device: str = "cpu",
                 decimation: int | None = None, chunk_size: int | None = None):
        self._init_common(model, num_worlds, decimation)
        if isinstance(nthread, bool) or not isinstance(nthread, int) or nthread < 0:
            raise PipelineInputError("backend", "nthread", f"must be an integer >= 0, got {nthread!r}")
        m, n, steps = self.model, self.num_worlds, self.decimation
        self.nthread = nthread
        self.device = torch.device(device)
        self._pool = mj_rollout.Rollout(nthread=nthread)
        self._scratch = [mujoco.MjData(m) for _ in range(max(1, nthread))]  # one per pool thread
        self._models: list[mujoco.MjModel] = [m] * n
        self._own_model = np.zeros(n, dtype=bool)  # worlds that hold a private copy
        # rollout's default chunk (N / (10 nthread)) balances the threads; keep it unless asked.
        self._chunk_size = chunk_size

        self._nstate = mujoco.mj_stateSize(m, _STATE_SPEC)
        _, self._qpos_at, self._qvel_at = state_offsets(m)
        self._state0 = np.zeros((n, self._nstate))                 # start of the next step
        self._states = np.zeros((n, steps, self._nstate))          # rollout output, per substep
        self._sensors = np.zeros((n, steps, m.nsensordata))        # rollout output, per substep
        self._ctrl = np.zeros((n, steps, m.nu))                    # float64 targets fed to rollout

        # torch views (float32 on `device`) and their numpy twins on the CPU for in-place copies
        num_sites = self.layout.num_sites
        self._host = {
            "qpos": torch.zeros(n, m.nq), "qvel": torch.zeros(n, m.nv),
            "site_pos": torch.zeros(n, num_sites, 3), "site_quat": torch.zeros(n, num_sites, 4),
            "foot_contact": torch.zeros(n, 2, dtype=torch.bool), "actuator_force": torch.zeros(n, m.nu),
        }
        self._np = {k: v.numpy() for k, v in self._host.items()}
        on_cpu = self.device.type == "cpu"
        for key, tensor in self._host.items():
            setattr(self, key, tensor if on_cpu else tensor.to(self.device))
        self._qpos64 = self._state0[:, self._qpos_at:self._qpos_at + m.nq]
        self._qvel64 = self._state0[:, self._qvel_at:self._qvel_at + m.nv]
        self._sensors_last = self._sensors[:, -1]
        (self._sp0, self._sp1), (self._sq0, self._sq1) = self.layout.site_pos, self.layout.site_quat
        (self._fc0, self._fc1), (self._af0, self._af1) = self.layout.foot_contact, self.layout.actuator_force

        # Start every world at the model's home pose, at rest, with targets holding that pose.
        home = default_state_qpos(m)
        self._ctrl[:] = home[m.jnt_qposadr[m.actuator_trnid[:, 0]]]
        self.set_state(np.arange(n), np.tile(home, (n, 1)), np.zeros((n, m.nv)))

    # ---- stepping ----

    def step(self, ctrl: torch.Tensor) -> None:
        per_substep = self._check_ctrl(ctrl)
        src = ctrl.detach()
        if src.device.type != "cpu":
            src = src.cpu()
        src = src.numpy()
        if per_substep:
            np.copyto(self._ctrl, src)
        else:
            np.copyto(self._ctrl, src[:, None, :])
        if not np.isfinite(self._ctrl).all():
            raise PipelineInputError("backend", "ctrl", "contains NaN/inf")
        self._pool.rollout(
            self._models, self._scratch, self._state0, self._ctrl,
            control_spec=_CTRL_SPEC, skip_checks=True, nstep=self.decimation,
            state=self._states, sensordata=self._sensors, chunk_size=self._chunk_size,
        )
        np.copyto(self._state0, self._states[:, -1])
        self._refresh_state_views()
        self._refresh_sensor_views(self._sensors_last)
        self._push_to_device()

    def _refresh_state_views(self) -> None:
        np.copyto(self._np["qpos"], self._qpos64, casting="same_kind")
        np.copyto(self._np["qvel"], self._qvel64, casting="same_kind")

    def _refresh_sensor_views(self, sensors: np.ndarray, rows=slice(None)) -> None:
        n = self.num_worlds if isinstance(rows, slice) else len(rows)
        views = self._np
        if isinstance(rows, slice):
            np.copyto(views["site_pos"].reshape(n, -1), sensors[:, self._sp0:self._sp1], casting="same_kind")
            np.copyto(views["site_quat"].reshape(n, -1), sensors[:, self._sq0:self._sq1], casting="same_kind")
            np.greater(sensors[:, self._fc0:self._fc1], 0.0, out=views["foot_contact"])
            np.copyto(views["actuator_force"], sensors[:, self._af0:self._af1], casting="same_kind")
        else:
            views["site_pos"][rows] = sensors[:, self._sp0:self._sp1].reshape(n, -1, 3)
            views["site_quat"][rows] = sensors[:, self._sq0:self._sq1].reshape(n, -1, 4)
            views["foot_contact"][rows] = sensors[:, self._fc0:self._fc1] > 0.0
            views["actuator_force"][rows] = sensors[:, self._af0:self._af1]

    def _push_to_device(self) -> None:
        if self.device.type == "cpu":
            return
        for key, host in self._host.items():
            getattr(self, key).copy_(host, non_blocking=True)

    # ---- state ----

    def set_state(self, world_ids, qpos, qvel, *, forward: bool = True) -> None:
        ids = self._world_ids(world_ids)
        qpos, qvel = self._check_state(len(ids), qpos, qvel)
        if len(ids) == 0:
            return
        self._state0[ids] = 0.0  # time, act, history... start afresh
        self._state0[ids, self._qpos_at:self._qpos_at + self.nq] = qpos
        self._state0[ids, self._qvel_at:self._qvel_at + self.nv] = qvel
        self._np["qpos"][ids] = qpos
        self._np["qvel"][ids] = qvel
        if forward:
            # Derived views for the new states: mj_forward per reset world on one scratch MjData.
            # Only reset worlds loop here (a few per step); actuator forces use the last targets.
            data = self._scratch[0]
            sensors = np.empty((len(ids), self.model.nsensordata))
            for row, world in enumerate(ids.tolist()):
                model = self._models[world]
                mujoco.mj_setState(model, data, self._state0[world], _STATE_SPEC)
                data.ctrl[:] = self._ctrl[world, -1]
                mujoco.mj_forward(model, data)
                sensors[row] = data.sensordata
            self._refresh_sensor_views(sensors, rows=ids)
        self._push_to_device()

    def get_state(self, world_ids=None) -> tuple[np.ndarray, np.ndarray]:
        # the float64 integrator state, not the float32 views: a resume must continue bit for bit
        ids = np.arange(self.num_worlds) if world_ids is None else self._world_ids(world_ids)
        return self._qpos64[ids].copy(), self._qvel64[ids].copy()

    # ---- per-world model parameters ----

    def set_model_field(self, name: str, world_ids, values) -> None:
        ids, values, _ = self._field_update(name, world_ids, values)
        for row, world in enumerate(ids.tolist()):
            model = self._own(world)
            getattr(model, name)[...] = values[row]
            if name == "geom_size":
                rbound, half = geom_bounds(model.geom_type, model.geom_size)
                model.geom_rbound[:] = rbound
                model.geom_aabb[:, 3:] = half
            if name in _STATIC_GEOM_FIELDS:
                refresh_body_bvh(model, 0)  # terrain geoms live on the world body

    def get_model_field(self, name: str, world_ids) -> np.ndarray:
        self._check_field(name)
        ids = self._world_ids(world_ids)
        return np.stack([np.array(getattr(self._models[w], name)) for w in ids.tolist()])

    def _own(self, world: int) -> mujoco.MjModel:
        if not self._own_model[world]:
            self._models[world] = copy.copy(self.model)
            self._own_model[world] = True
        return self._models[world]

    def world_model(self, world: int) -> mujoco.MjModel:
        """World `world`'s model (shared with others until it is randomised): read it, don't write."""
        return self._models[world]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
