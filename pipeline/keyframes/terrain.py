"""Terrain per task and ψ, as cheap MuJoCo boxes (and planes) with one model structure per task.

  * flat — the plane `ground`;
  * gap  — boxes `terrain_box_0..G` with a gap before each edited landing (far jump: one, triple
    jump: three) and the plane `terrain_pit` `depth` below;
  * step — boxes `terrain_box_0..G` whose tops change at each edited landing (step up / down).

Geometry comes from the motion once (`resolve_terrain`, stored in `TrackingData.terrain`): along the
edit direction, each gap runs from the takeoff toes (+ margin) to the landing heels (− margin) of the
feet that stand in the stances around it (a hop's swinging foot, ahead of its take-off, edges nothing), and
each moves with its keyframes as ψ changes, so the edited reference always lands just beyond the
gap. A box between two gaps moves with its keyframes without changing length, so for the paper's
tasks `terrain_layout` changes positions only; sizes are reported too (the contract), constant.
A step's height is the edited reference's own floor (`height: reference`, default) or ±ψ (`psi`).
"""

from __future__ import annotations

from typing import Callable

import mujoco
import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.config import TaskConfig, TerrainConfig
from pipeline.keyframes.tracking_data import TrackingData

FAR = 20.0  # m: the first and last box reach this far beyond the edits
HALF_WIDTH = 10.0  # m: lateral half-width of every box
STEP_HALF_HEIGHT = 1.0  # m: half-thickness of step boxes (enough for ±0.5 m steps)
BOX_RGBA = [0.42, 0.45, 0.5, 1.0]


def _edit_shares(keyframes) -> np.ndarray:
    edited = keyframes.edited.astype(float)
    return np.cumsum(edited) / max(edited.sum(), 1.0)


def resolve_terrain(task: TaskConfig, motion, keyframes) -> dict:
    """The task's terrain declaration with its anchors measured on the motion (JSON-ready)."""
    from pipeline.keyframes.edit import edit_direction
    from pipeline.motion.feet import detect_foot_contacts, foot_height_and_speed, sole_points_world

    cfg = task.terrain
    out = cfg.to_dict()
    if cfg.kind == "flat":
        return out
    src, fld = f"task {task.name}", "terrain"
    if cfg.anchors:  # declared by the user: trusted, checked by the layout
        out["anchors"] = {"psi_raw": task.psi.raw, "sign": task.edit.sign, **cfg.anchors}
        return out
    if cfg.kind == "gap":
        direction = edit_direction(motion, task.edit.mode)[:2]
    else:  # a step lies across the travel from start to landing
        travel = motion.root_pos[-1, :2] - motion.root_pos[0, :2]
        direction = travel / np.linalg.norm(travel) if np.linalg.norm(travel) > 0.05 else np.array([1.0, 0.0])
    direction = direction / np.linalg.norm(direction)
    soles = sole_points_world(motion)[..., :2] @ direction  # (T, 2, P) along the axis
    height, _ = foot_height_and_speed(motion)
    contact = detect_foot_contacts(motion)

    flight_frames = [(a, b) for a, b in getattr(keyframes, "flights", ())] or [
        (int(f), int(f)) for f in keyframes.frames]

    def stance_edge(frame: int, side: str) -> float:
        """Along the axis: the toes furthest forward of the feet that last stood in the stance ending at
        take-off `frame` ("takeoff"), or the heels furthest back of the feet that first stand in the
        stance starting at landing `frame` ("landing"), each foot where it stood or stands. A hop's
        swinging foot, ahead of the take-off and behind the landing, edges nothing; a foot coming
        down after the other edges where it lands."""
        if side == "takeoff":
            start = max([b for _, b in flight_frames if b <= frame], default=0)
            span = range(frame, start - 1, -1)
        else:
            stop = min([a for a, _ in flight_frames if a >= frame], default=motion.num_frames - 1)
            span = range(frame, stop + 1)
        edges = []
        for foot in range(2):
            stood = next((f for f in span if contact[f, foot]), None)
            if stood is not None:
                edges.append(soles[stood, foot].max() if side == "takeoff" else soles[stood, foot].min())
        if not edges:  # nothing found on the ground there (flights listed by hand): the lowest foot
            foot = int(np.argmin(height[frame]))
            edges.append(soles[frame, foot].max() if side == "takeoff" else soles[frame, foot].min())
        return float(max(edges) if side == "takeoff" else min(edges))

    shares = _edit_shares(keyframes)
    frames, labels = keyframes.frames, keyframes.labels
    edited_idx = np.flatnonzero(keyframes.edited)
    if len(edited_idx) == 0:
        raise PipelineInputError(src, fld, f"{cfg.kind} terrain needs an edited landing keyframe")
    anchors: dict = {"direction": direction.tolist(), "psi_raw": task.psi.raw, "sign": task.edit.sign}
    if cfg.kind == "gap":
        gaps = []
        for k in edited_idx:
            before = [i for i in range(k) if labels[i].startswith("takeoff")]
            if not before:
                raise PipelineInputError(src, fld, f"a gap needs a takeoff keyframe before the edited "
                                                   f"keyframe at {keyframes.times[k]:.2f} s; none found")
            t = before[-1]
            takeoff, landing = stance_edge(frames[t], "takeoff"), stance_edge(frames[k], "landing")
            if landing < takeoff:
                raise PipelineInputError(
                    src, fld, f"{task.input}: the gap before {labels[k]} would run backwards: the landing heels "
                    f"({keyframes.times[k]:.2f} s) are {takeoff - landing:.2f} m behind the take-off toes "
                    f"({labels[t]}, {keyframes.times[t]:.2f} s) along the jump ({landing:.2f} m against "
                    f"{takeoff:.2f} m): these two keyframes are not one jump forward. Check the flights found "
                    f"(keyframes.json `flights`) and list them by hand if they are wrong (keyframes.flights)")
            gaps.append({"takeoff": takeoff, "landing": landing,
                         "takeoff_share": float(shares[t]), "landing_share": float(shares[k])})
        anchors["gaps"] = gaps
    else:
        steps = []
        for k in edited_idx:
            window = slice(frames[k], min(frames[k] + 4, motion.num_frames))
            steps.append({"edge": stance_edge(frames[k], "landing") - cfg.margin,
                          "floor": float(np.median(height[window].min(axis=1))), "share": float(shares[k])})
        anchors["steps"] = steps
        anchors["start_floor"] = float(height[0].min())
    out["anchors"] = anchors
    # Unbuildable geometry (a gap running backwards, gaps overlapping) fails here, before any work, at
    # ψ_raw and at both ends of the training range.
    for psi in (task.psi.raw, min(lo for lo, _ in task.psi.train), max(hi for _, hi in task.psi.train)):
        terrain_layout(out, psi, source=src)
    return out


def _resolved(task) -> tuple[dict, str]:
    if isinstance(task, TrackingData):
        return task.terrain or {"kind": "flat"}, f"task {task.task}"
    if isinstance(task, TaskConfig):
        terrain = task.terrain.to_dict()
        if terrain["kind"] != "flat" and terrain["anchors"]:
            terrain["anchors"] = {"psi_raw": task.psi.raw, "sign": task.edit.sign, **terrain["anchors"]}
        return terrain, f"task {task.name}"
    if isinstance(task, TerrainConfig):
        return task.to_dict(), "terrain"
    if isinstance(task, dict):
        return task, "terrain"
    raise TypeError(f"terrain of a TaskConfig, TrackingData or terrain dict, not {type(task).__name__}")


def _segments(terrain: dict, psi: float, src: str) -> list[tuple[float, float, float]]:
    """(lo, hi, top) of each box along the axis for ψ."""
    a = terrain.get("anchors") or {}
    margin = float(terrain.get("margin", TerrainConfig.margin))
    if "psi_raw" not in a:
        raise PipelineInputError(src, "terrain.anchors", f"{terrain['kind']} terrain has no anchors yet: build it "
                                 "from TrackingData.terrain (build_tracking_data) or declare terrain.anchors")
    delta = float(a.get("sign", 1.0)) * (psi - float(a["psi_raw"]))
    if terrain["kind"] == "gap":
        gaps = a.get("gaps") or []
        if not gaps:
            raise PipelineInputError(src, "terrain.anchors.gaps", "a gap terrain needs at least one gap")
        edges = []
        for i, g in enumerate(gaps):
            if g["landing"] < g["takeoff"]:
                raise PipelineInputError(src, f"terrain.anchors.gaps[{i}]", f"the landing edge ({g['landing']:.2f} m) "
                                         f"lies behind the take-off edge ({g['takeoff']:.2f} m): a gap cannot run backwards")
            start = g["takeoff"] + g.get("takeoff_share", 0.0) * delta + margin
            end = max(start, g["landing"] + g.get("landing_share", 1.0) * delta - margin)  # ψ small: no gap
            edges.append((start, end))
        segs = [(edges[0][0] - FAR, edges[0][0], 0.0)]
        for (_, prev_end), (start, _) in zip(edges, edges[1:]):
            if start - prev_end <= 0.05:
                raise PipelineInputError(src, "terrain", f"at ψ = {psi:g} the ground between two gaps would be "
                                         f"{start - prev_end:.2f} m long: the next take-off lies before the "
                                         "last landing (the gaps overlap)")
            segs.append((prev_end, start, 0.0))
        segs.append((edges[-1][1], edges[-1][1] + FAR, 0.0))
        return segs
    if terrain["kind"] == "step":
        steps = a.get("steps") or []
        if not steps:
            raise PipelineInputError(src, "terrain.anchors.steps", "a step terrain needs at least one step")
        base = float(a.get("start_floor", 0.0))
        edges = [s["edge"] for s in steps]
        if any(b - e <= 0.05 for e, b in zip(edges, edges[1:])):
            raise PipelineInputError(src, "terrain", f"step edges {edges} are not increasing along the travel")
        tops = [base]
        for s in steps:
            if terrain.get("height", "reference") == "psi":
                tops.append(float(a.get("sign", 1.0)) * psi * s.get("share", 1.0))
            else:
                tops.append(s["floor"] + s.get("share", 1.0) * delta)
        if max(abs(t) for t in tops) > STEP_HALF_HEIGHT * 1.5:
            raise PipelineInputError(src, "terrain", f"step tops {np.round(tops, 3).tolist()} m exceed ±1.5 m")
        bounds = [edges[0] - FAR] + edges + [edges[-1] + FAR]
        return [(bounds[i], bounds[i + 1], tops[i]) for i in range(len(tops))]
    raise PipelineInputError(src, "terrain.kind", f"unknown terrain {terrain['kind']!r}")


def terrain_layout(task, psi: float, *, source: str | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per-ψ pos (3,) and half-size (3,) of each geom `terrain_builder` made. Flat: {}."""
    terrain, src = _resolved(task)
    src = source or src
    if terrain["kind"] == "flat":
        return {}
    direction = np.asarray((terrain.get("anchors") or {}).get("direction", [1.0, 0.0]), float)
    half_h = terrain.get("depth", 0.6) / 2 if terrain["kind"] == "gap" else STEP_HALF_HEIGHT
    layout = {}
    for i, (lo, hi, top) in enumerate(_segments(terrain, float(psi), src)):
        mid = 0.5 * (lo + hi)
        pos = np.array([direction[0] * mid, direction[1] * mid, top - half_h])
        layout[f"terrain_box_{i}"] = (pos, np.array([0.5 * (hi - lo), HALF_WIDTH, half_h]))
    return layout


def terrain_builder(task) -> Callable[[mujoco.MjSpec], None]:
    """A `build_spec(terrain=...)` hook adding the task's ground, laid out for ψ_raw."""
    terrain, src = _resolved(task)
    kind = terrain.get("kind", "flat")
    if kind not in ("flat", "gap", "step"):
        raise PipelineInputError(src, "terrain.kind", f"unknown terrain {kind!r}")
    if kind == "flat":
        from pipeline.robot.g1 import add_flat_ground

        return add_flat_ground
    anchors = terrain.get("anchors") or {}
    layout = terrain_layout(terrain, float(anchors.get("psi_raw", 0.0)), source=src)
    direction = np.asarray(anchors.get("direction", [1.0, 0.0]), float)
    yaw = float(np.arctan2(direction[1], direction[0]))
    box_quat = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]

    def build(spec: mujoco.MjSpec) -> None:
        if kind == "gap":
            spec.worldbody.add_geom(name="terrain_pit", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05],
                                    pos=[0, 0, -float(terrain.get("depth", 0.6))], rgba=[0.2, 0.2, 0.22, 1],
                                    contype=1, conaffinity=1, condim=3)
        for name, (pos, size) in layout.items():
            spec.worldbody.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, pos=pos.tolist(),
                                    size=size.tolist(), quat=box_quat, rgba=BOX_RGBA,
                                    contype=1, conaffinity=1, condim=3)

    return build


def apply_layout(model: mujoco.MjModel, layout: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """Moves/resizes the terrain geoms of one MjModel (a CPU world; the env does the same per world
    through `set_model_field`). Bounding radius and box are refreshed so collisions stay right."""
    for name, (pos, size) in layout.items():
        g = model.geom(name).id
        model.geom_pos[g] = pos
        model.geom_size[g] = size
        model.geom_rbound[g] = float(np.linalg.norm(size))
        model.geom_aabb[g] = np.concatenate([np.zeros(3), size])
