"""The narrow physics interface the tracking environment is written against (docs/INTERFACES.md).

A backend holds N worlds of one model structure. The environment only ever:
  * writes states of some worlds (`set_state`, which also makes the derived views current),
  * steps all worlds one control step with PD targets (`step`),
  * reads torch float32 views (`qpos`, `qvel`, `site_pos`, `site_quat`, `foot_contact`,
    `actuator_force`), refreshed in place, so a reference taken once stays valid,
  * changes per-world model parameters (`set_model_field`) for domain randomisation and terrain.

Timing of the derived views after `step` follows MuJoCo's mj_step: positions/velocities are the new
state; site poses, contacts and actuator forces were computed by the last substep's forward pass,
i.e. one substep (5 ms) before the new state. After `set_state` they are exact for the new state.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Sequence

import mujoco
import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.robot.g1 import load_robot_config
from pipeline.sim.model import check_actuators_in_joint_order, sensor_layout, sim_model_from

BACKENDS = ("cpu", "warp")
_SOURCE = "backend"


def decimation_for(model: mujoco.MjModel, control_dt: float | None = None) -> int:
    """Substeps per control step: the robot's control_dt over the model's timestep."""
    control_dt = load_robot_config().control_dt if control_dt is None else control_dt
    ratio = control_dt / float(model.opt.timestep)
    decimation = int(round(ratio))
    if decimation < 1 or abs(ratio - decimation) > 1e-6:
        raise PipelineInputError(_SOURCE, "decimation",
                                 f"control_dt {control_dt} is not a multiple of the timestep {model.opt.timestep}")
    return decimation


class PhysicsBackend(ABC):
    """N worlds of one MjModel. Subclasses fill the views in __init__ and keep them in place."""

    num_worlds: int
    nq: int
    nv: int
    nu: int
    decimation: int
    device: torch.device
    model: mujoco.MjModel
    site_names: tuple[str, ...]
    # Views, torch on `device`, updated in place by set_state/step.
    qpos: torch.Tensor            # (N, nq) float32
    qvel: torch.Tensor            # (N, nv) float32
    site_pos: torch.Tensor        # (N, S, 3) float32, world frame
    site_quat: torch.Tensor       # (N, S, 4) float32, wxyz
    foot_contact: torch.Tensor    # (N, 2) bool, (left, right)
    actuator_force: torch.Tensor  # (N, nu) float32

    def _init_common(self, model, num_worlds: int, decimation: int | None) -> None:
        model = sim_model_from(model)
        check_num_worlds(num_worlds)
        check_actuators_in_joint_order(model)
        self.model = model
        self.layout = sensor_layout(model)
        self.site_names = self.layout.site_names
        self.num_worlds = int(num_worlds)
        self.nq, self.nv, self.nu = model.nq, model.nv, model.nu
        self.decimation = decimation_for(model) if decimation is None else int(decimation)
        if self.decimation < 1:
            raise PipelineInputError(_SOURCE, "decimation", f"must be >= 1, got {self.decimation}")

    @abstractmethod
    def set_state(self, world_ids, qpos, qvel, *, forward: bool = True) -> None:
        """Sets qpos (n, nq) / qvel (n, nv) of worlds `world_ids` (n,) and recomputes their views.
        With forward=False only the qpos/qvel views change: the derived ones (sites, contacts,
        actuator forces) keep their old values until the next step, which computes them anyway. That
        saves a forward pass (on Warp one over every world) where nothing reads them in between."""

    @abstractmethod
    def step(self, ctrl: torch.Tensor) -> None:
        """One control step: ctrl (N, nu) held for all substeps, or (N, decimation, nu) per substep."""

    @abstractmethod
    def set_model_field(self, name: str, world_ids, values) -> None:
        """Sets MjModel field `name` (e.g. body_mass, geom_friction, actuator_gainprm, geom_size,
        geom_pos) for worlds `world_ids`; values (n, *field.shape) or broadcastable to it.
        Takes effect from the next step/set_state. Dependent constants (mj_setConst) are not recomputed,
        except the collision bounds of resized geoms."""

    @abstractmethod
    def get_model_field(self, name: str, world_ids) -> np.ndarray:
        """Per-world values of MjModel field `name`, (n, *field.shape), float64/int as in MjModel."""

    def get_state(self, world_ids=None) -> tuple[np.ndarray, np.ndarray]:
        """(qpos (n, nq), qvel (n, nv)) float64 of worlds `world_ids` (None: all), for checkpoints.
        This default reads the float32 views; a backend that integrates in float64 returns its own
        state so that set_state(get_state()) continues bit for bit."""
        ids = np.arange(self.num_worlds) if world_ids is None else self._world_ids(world_ids)
        return (self.qpos.detach().cpu().numpy().astype(np.float64)[ids],
                self.qvel.detach().cpu().numpy().astype(np.float64)[ids])

    def close(self) -> None:
        """Releases threads / device memory; the backend is unusable afterwards."""

    # ---- shared input checks (cheap: shape tuples and one isfinite) ----

    def _world_ids(self, world_ids) -> np.ndarray:
        ids = torch.as_tensor(world_ids).detach().cpu().numpy() if not isinstance(world_ids, np.ndarray) else world_ids
        if ids.dtype == bool:
            if ids.shape != (self.num_worlds,):
                raise PipelineInputError(_SOURCE, "world_ids", f"a mask must have shape ({self.num_worlds},)")
            return np.flatnonzero(ids)
        ids = np.asarray(ids).reshape(-1)
        if ids.size and (not np.issubdtype(ids.dtype, np.integer) or ids.min() < 0 or ids.max() >= self.num_worlds):
            raise PipelineInputError(_SOURCE, "world_ids", f"must be integers in [0, {self.num_worlds})")
        if np.unique(ids).size != ids.size:
            raise PipelineInputError(_SOURCE, "world_ids", "contains duplicates")
        return ids.astype(np.int64, copy=False)

    def _check_state(self, n: int, qpos, qvel) -> tuple[np.ndarray, np.ndarray]:
        qpos = _as_numpy64(qpos)
        qvel = _as_numpy64(qvel)
        if qpos.shape != (n, self.nq):
            raise PipelineInputError(_SOURCE, "qpos", f"expected shape ({n}, {self.nq}), got {qpos.shape}")
        if qvel.shape != (n, self.nv):
            raise PipelineInputError(_SOURCE, "qvel", f"expected shape ({n}, {self.nv}), got {qvel.shape}")
        if not (np.isfinite(qpos).all() and np.isfinite(qvel).all()):
            raise PipelineInputError(_SOURCE, "qpos/qvel", "contains NaN/inf")
        return qpos, qvel

    def _check_ctrl(self, ctrl: torch.Tensor) -> bool:
        """True if ctrl holds one target per substep; raises on a bad shape."""
        shape = tuple(ctrl.shape)
        if shape == (self.num_worlds, self.nu):
            return False
        if shape == (self.num_worlds, self.decimation, self.nu):
            return True
        raise PipelineInputError(
            _SOURCE, "ctrl",
            f"expected ({self.num_worlds}, {self.nu}) or ({self.num_worlds}, {self.decimation}, {self.nu}), got {shape}")

    def _check_field(self, name: str) -> np.ndarray:
        template = getattr(self.model, name, None)
        if not isinstance(template, np.ndarray) or template.dtype.kind not in "fiu":
            raise PipelineInputError(_SOURCE, "set_model_field", f"{name!r} is not a numeric MjModel array field")
        return template

    def _field_update(self, name: str, world_ids, values) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Checked (ids, values (n, *field.shape), template) for set_model_field."""
        template = self._check_field(name)
        ids = self._world_ids(world_ids)
        try:
            values = np.broadcast_to(_as_numpy64(values), (len(ids), *template.shape))
        except ValueError as err:
            raise PipelineInputError(_SOURCE, name, f"values must broadcast to ({len(ids)}, {template.shape}): {err}")
        return ids, values, template


def _as_numpy64(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def check_num_worlds(num_worlds) -> None:
    if isinstance(num_worlds, bool) or not isinstance(num_worlds, (int, np.integer)) or num_worlds <= 0:
        raise PipelineInputError(_SOURCE, "num_worlds", f"must be a positive integer, got {num_worlds!r}")


def cuda_available() -> bool:
    return torch.cuda.is_available()


def make_backend(
    name: str,
    model: mujoco.MjModel | mujoco.MjSpec,
    num_worlds: int,
    *,
    nthread: int = 2,
    device: str | None = None,
    allow_warp_on_cpu: bool = False,
    **kwargs,
) -> PhysicsBackend:
    """Builds a backend by name ("cpu" or "warp"), with clear errors for bad input.

    `device` is where the torch views live: "cpu" by default for the CPU backend, "cuda" for warp.
    Warp on CPU is slow (about 0.5k steps/s) and only meant for tests: pass allow_warp_on_cpu=True.
    """
    if name not in BACKENDS:
        raise PipelineInputError(_SOURCE, "name", f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    check_num_worlds(num_worlds)
    if name == "cpu":
        from pipeline.sim.cpu import CpuBackend

        return CpuBackend(model, num_worlds, nthread=nthread, device=device or "cpu", **kwargs)
    device = device or "cuda"
    if device.startswith("cuda") and not cuda_available():
        raise PipelineInputError(_SOURCE, "device", "the warp backend needs a CUDA GPU and none is available "
                                 "(use backend 'cpu', or device='cpu' with allow_warp_on_cpu=True for tests)")
    if device == "cpu" and not allow_warp_on_cpu:
        raise PipelineInputError(_SOURCE, "device", "warp on CPU is only for tests: pass allow_warp_on_cpu=True")
    from pipeline.sim.warp import WarpBackend

    return WarpBackend(model, num_worlds, device=device, **kwargs)


def as_id_list(world_ids: Sequence[int] | np.ndarray) -> list[int]:
    return [int(i) for i in np.asarray(world_ids).reshape(-1)]
