"""WarpBackend: N worlds on MuJoCo Warp (GPU; also runs on CPU, slowly, for the equivalence test).

  * Same MJCF and sensors as the CPU backend (pipeline.sim.model); `mjw.put_model` / `put_data`
    with nworld = N.
  * Contact and constraint buffers are sized per world (nconmax / njmax per world; mujoco_warp
    multiplies by nworld). Sizing them by the total (naconmax) made every kernel loop over the
    whole pool and was about 10x slower.
  * Per-world parameters: mujoco_warp Model fields whose spec starts with "*" have a leading batch
    axis indexed by world (size 1 = shared). `put_model(batch_sizes=...)` gives the fields listed
    in PER_WORLD_FIELDS one row per world up front; any other batchable field is expanded on its
    first `set_model_field` (which re-records the CUDA graph, since the array moves).
  * The torch views alias Warp's arrays (wp.to_torch, no copies): qpos/qvel directly, site poses
    and actuator forces as slices of sensordata; only foot_contact (bool) is computed per step.
  * On CUDA the substep loop (control copy + mjw.step, x decimation) is captured once as a CUDA
    graph and replayed each step.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.sim.backend import PhysicsBackend
from pipeline.sim.model import default_state_qpos, geom_bounds

# Fields domain randomisation and terrain layouts write (issue 5's table + terrain per ψ).
PER_WORLD_FIELDS = (
    "body_mass", "body_ipos", "geom_friction", "geom_solref", "actuator_gainprm", "actuator_biasprm",
    "geom_pos", "geom_size", "geom_rbound", "geom_aabb",
)
# Per-world buffer sizes. Standing/walking G1: <= 14 foot contacts; a fallen robot touches with
# more geoms. njmax: pyramidal friction gives 2(condim-1) rows per condim-3 contact, plus joint limits.
DEFAULT_NCONMAX = 48
DEFAULT_NJMAX = 256


class WarpBackend(PhysicsBackend):
    def __init__(self, model, num_worlds: int, *, device: str = "cuda", decimation: int | None = None,
                 nconmax: int = DEFAULT_NCONMAX, njmax: int = DEFAULT_NJMAX,
                 per_world_fields: tuple[str, ...] = PER_WORLD_FIELDS, use_graph: bool | None = None):
        import mujoco_warp as mjw
        import warp as wp

        self._init_common(model, num_worlds, decimation)
        self._wp, self._mjw = wp, mjw
        wp.init()
        self._wp_device = wp.get_device("cpu" if device == "cpu" else device)
        self.device = torch.device("cpu" if self._wp_device.is_cpu else f"cuda:{self._wp_device.ordinal}")
        self._use_graph = (not self._wp_device.is_cpu) if use_graph is None else bool(use_graph)
        m, n = self.model, self.num_worlds

        with wp.ScopedDevice(self._wp_device):
            self._m = mjw.put_model(m, batch_sizes={name: n for name in per_world_fields})
            data = mujoco.MjData(m)
            data.qpos[:] = default_state_qpos(m)
            data.ctrl[:] = data.qpos[m.jnt_qposadr[m.actuator_trnid[:, 0]]]
            mujoco.mj_forward(m, data)
            self._d = mjw.put_data(m, data, nworld=n, nconmax=int(nconmax), njmax=int(njmax))
        self.nconmax, self.njmax = int(nconmax), int(njmax)

        to_torch = wp.to_torch
        self.qpos = to_torch(self._d.qpos)
        self.qvel = to_torch(self._d.qvel)
        self._ctrl_now = to_torch(self._d.ctrl)
        self._warmstart = to_torch(self._d.qacc_warmstart)
        self._time = to_torch(self._d.time)
        sensors = to_torch(self._d.sensordata)
        L = self.layout
        self.site_pos = sensors[:, L.site_pos[0]:L.site_pos[1]].view(n, L.num_sites, 3)
        self.site_quat = sensors[:, L.site_quat[0]:L.site_quat[1]].view(n, L.num_sites, 4)
        self.actuator_force = sensors[:, L.actuator_force[0]:L.actuator_force[1]]
        self._contact_found = sensors[:, L.foot_contact[0]:L.foot_contact[1]]
        self.foot_contact = torch.zeros(n, 2, dtype=torch.bool, device=self.device)

        # Per-substep targets, substep-major so each substep's block is contiguous for wp.copy.
        self._ctrl_buf = torch.zeros(self.decimation, n, m.nu, dtype=torch.float32, device=self.device)
        self._ctrl_buf[:] = self._ctrl_now
        self._ctrl_blocks = [wp.from_torch(self._ctrl_buf[k]) for k in range(self.decimation)]
        self._step_graph = None
        self._forward_graph = None
        self._refresh_contacts()

    # ---- stepping ----

    def _substeps(self) -> None:
        for block in self._ctrl_blocks:
            self._wp.copy(self._d.ctrl, block)
            self._mjw.step(self._m, self._d)

    def _forward(self) -> None:
        self._mjw.forward(self._m, self._d)

    def _run(self, fn, graph_attr: str) -> None:
        wp = self._wp
        with wp.ScopedDevice(self._wp_device):
            if not self._use_graph:
                fn()
                return
            graph = getattr(self, graph_attr)
            if graph is None:
                fn()  # this call's work; it also loads the kernels, which a capture cannot do
                with wp.ScopedCapture() as capture:  # records only, runs nothing
                    fn()
                setattr(self, graph_attr, capture.graph)
                return
            wp.capture_launch(graph)

    def step(self, ctrl: torch.Tensor) -> None:
        per_substep = self._check_ctrl(ctrl)
        ctrl = ctrl.detach().to(device=self.device, dtype=torch.float32)
        if not torch.isfinite(ctrl).all():
            raise PipelineInputError("backend", "ctrl", "contains NaN/inf")
        if per_substep:
            self._ctrl_buf.copy_(ctrl.transpose(0, 1))
        else:
            self._ctrl_buf.copy_(ctrl.unsqueeze(0).expand(self.decimation, -1, -1))
        self._run(self._substeps, "_step_graph")
        self._refresh_contacts()

    def _refresh_contacts(self) -> None:
        torch.gt(self._contact_found, 0.0, out=self.foot_contact)

    # ---- state ----

    def set_state(self, world_ids, qpos, qvel, *, forward: bool = True) -> None:
        ids = self._world_ids(world_ids)
        qpos, qvel = self._check_state(len(ids), qpos, qvel)
        if len(ids) == 0:
            return
        index = torch.as_tensor(ids, device=self.device)
        self.qpos[index] = torch.as_tensor(qpos, dtype=torch.float32, device=self.device)
        self.qvel[index] = torch.as_tensor(qvel, dtype=torch.float32, device=self.device)
        self._warmstart[index] = 0.0
        self._time[index] = 0.0
        if not forward:
            return
        # mjw.forward has no world mask: it refreshes every world's derived quantities at its
        # current state (the state itself is untouched), which is one forward pass per call, so
        # call set_state once per step with all the worlds to reset.
        self._run(self._forward, "_forward_graph")
        self._refresh_contacts()

    # ---- per-world model parameters ----

    def _field(self, name: str) -> torch.Tensor:
        """(N or 1, ...) torch view of mujoco_warp's model field `name`, expanded to N if needed."""
        wp = self._wp
        array = getattr(self._m, name, None)
        if array is None or not isinstance(array, wp.array):
            raise PipelineInputError("backend", "set_model_field", f"{name!r} is not a mujoco_warp Model array")
        view = wp.to_torch(array)
        if view.shape[0] != self.num_worlds:
            spec = next(f.type for f in dataclasses.fields(type(self._m)) if f.name == name)
            spec_shape = getattr(spec, "shape", ())
            if not spec_shape or spec_shape[0] != "*":
                raise PipelineInputError("backend", "set_model_field", f"{name!r} cannot differ between worlds in mujoco_warp")
            with wp.ScopedDevice(self._wp_device):
                expanded = wp.array(view.expand(self.num_worlds, *view.shape[1:]).contiguous(), dtype=array.dtype)
            setattr(self._m, name, expanded)
            self._step_graph = self._forward_graph = None  # the graphs hold the old array's address
            view = wp.to_torch(expanded)
        return view

    def set_model_field(self, name: str, world_ids, values) -> None:
        ids, values, _ = self._field_update(name, world_ids, values)
        view = self._field(name)
        index = torch.as_tensor(ids, device=self.device)
        view[index] = torch.as_tensor(np.array(values), dtype=view.dtype, device=self.device).reshape(len(ids), *view.shape[1:])
        if name == "geom_size":
            types = self.model.geom_type
            rbound = np.empty((len(ids), self.model.ngeom))
            half = np.empty((len(ids), self.model.ngeom, 3))
            for row in range(len(ids)):
                rbound[row], half[row] = geom_bounds(types, values[row])
            self._field("geom_rbound")[index] = torch.as_tensor(rbound, dtype=torch.float32, device=self.device)
            self._field("geom_aabb")[index, :, 1] = torch.as_tensor(half, dtype=torch.float32, device=self.device)

    def get_model_field(self, name: str, world_ids) -> np.ndarray:
        template = self._check_field(name)
        ids = self._world_ids(world_ids)
        view = self._wp.to_torch(getattr(self._m, name))
        if view.shape[0] == self.num_worlds:
            rows = view[torch.as_tensor(ids, device=self.device)]
        else:
            rows = view.expand(len(ids), *view.shape[1:])
        return rows.cpu().numpy().astype(template.dtype).reshape(len(ids), *template.shape)

    def contact_overflow(self) -> bool:
        """True if some world hit its contact buffer since the data was made (then raise nconmax)."""
        nacon = int(self._wp.to_torch(self._d.nacon).max().item())
        return nacon >= self.nconmax * self.num_worlds

    def close(self) -> None:
        self._step_graph = self._forward_graph = None
