"""The scene every world of the tracking env simulates: the G1 on the task's terrain, its physics backend,
and the terrain's per-ψ-sample geometry that a reset writes into each world's model.

Terrain comes from `pipeline.keyframes.terrain`: `terrain_builder(task)` adds the task's geoms to the
scene once, and `terrain_layout(task, ψ)` says where they sit for one ψ (a far jump's landing
platform moves with the gap; a step's height is ψ). Flat ground needs neither.
"""

from __future__ import annotations

from typing import Callable

import mujoco
import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.tracking_data import TrackingData

Layout = Callable[[float], dict]


def build_scene(data: TrackingData, task, source: str, physics: str | None = None) -> tuple[mujoco.MjModel, Layout | None]:
    """The compiled scene for `data`'s terrain under physics preset `physics` (robot.yaml; None: its
    default) and its ψ -> layout function (None on flat ground)."""
    from pipeline.robot.g1 import load_robot_config

    preset = load_robot_config().physics(physics, source, "env.physics")  # a bad name is the env config's fault
    builder, layout = _terrain_hooks(data, task, source)
    try:
        from pipeline.sim.model import build_sim_model

        model = build_sim_model(terrain=builder, physics=preset)
    except Exception as exc:  # a terrain that does not compile is the task's fault
        raise PipelineInputError(source, "terrain", f"cannot build the scene: {exc}") from exc
    return model, layout


def make_physics(backend, model: mujoco.MjModel, num_envs: int, nthread: int, device, source: str):
    """A `PhysicsBackend` by name ("cpu": MuJoCo C on threads, "warp": MuJoCo Warp), or `backend` itself
    when it already is one (tests, custom engines)."""
    if not isinstance(backend, str):
        return backend
    if backend not in ("cpu", "warp"):
        raise PipelineInputError(source, "backend", f"unknown backend {backend!r} (known: cpu, warp)")
    from pipeline.sim.backend import make_backend

    try:
        return make_backend(backend, model, num_envs, nthread=nthread, device=str(device))
    except PipelineInputError:
        raise
    except (ValueError, RuntimeError, ImportError) as exc:
        raise PipelineInputError(source, "backend", f"cannot start {backend!r}: {exc}") from exc


def terrain_fields_per_sample(model: mujoco.MjModel, layout: Layout | None, psi, source: str):
    """(geom_pos (S, ngeom, 3), geom_size (S, ngeom, 3) or None) of the whole model for each ψ sample, or
    None when the terrain never moves. Sizes are None when no sample changes them (the paper's tasks):
    a reset then writes positions only, as resizing also makes the backend recompute collision bounds."""
    if layout is None:
        return None
    layouts = [layout(float(p)) for p in psi]
    if not layouts or not layouts[0]:
        return None
    names = sorted(layouts[0])
    try:
        ids = [model.geom(name).id for name in names]
    except KeyError as exc:
        raise PipelineInputError(source, "terrain", f"layout names an unknown geom: {exc}") from exc
    pos = np.repeat(model.geom_pos[None], len(layouts), 0).copy()
    size = np.repeat(model.geom_size[None], len(layouts), 0).copy()
    for s, lay in enumerate(layouts):
        for gid, name in zip(ids, names):
            pos[s, gid], size[s, gid] = lay[name]
    return pos, (size if np.ptp(size, axis=0).max() > 0 else None)


def _terrain_hooks(data: TrackingData, task, source: str):
    """(builder, layout(ψ)) for `data`'s terrain, each failure a PipelineInputError naming the terrain;
    (None, None) on flat ground."""
    if not data.terrain or data.terrain.get("kind", "flat") == "flat":
        return None, None
    from pipeline.keyframes import terrain

    # The hooks take the task (TaskConfig) or, without one, the TrackingData and its resolved terrain.
    task = task if task is not None else data
    try:
        builder = terrain.terrain_builder(task)
    except PipelineInputError:
        raise
    except Exception as exc:
        raise PipelineInputError(source, "terrain", f"cannot build the terrain: {exc}") from exc

    def layout(psi: float):
        try:
            return terrain.terrain_layout(task, psi)
        except PipelineInputError:
            raise
        except Exception as exc:
            raise PipelineInputError(source, "terrain", f"cannot lay out ψ={psi}: {exc}") from exc

    return builder, layout
