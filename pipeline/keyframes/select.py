"""Keyframe selection: semantic keyframes found in the motion, uniform ones filling the rest.

Semantic events (beyond the paper, which hand-picks keyframes):
  * foot contacts from the tracked ankle bodies' poses: the lowest point of each foot's sole (the
    G1 foot capsules placed with the ankle's pose) and that point's speed;
  * takeoff = last frame with a foot in contact before a flight, landing = first frame after it
    (flight: no foot in contact for at least `min_flight` seconds);
  * apex = highest root inside a flight; hit = peak wrist speed.
Uniform keyframes every `spacing` seconds fill the rest, but never inside a flight: an unedited
target in mid-air would contradict every edited landing (the paper's far jump has none there).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import mujoco
import numpy as np

from pipeline.common import quat
from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.config import DEFAULT_EDITED, KeyframeSpec, TaskConfig, _selector_hits
from pipeline.motion.motion import Motion

STILL_SPEED = 0.25  # m/s: a sole point slower than this may be planted
STILL_FRAMES_S = 0.05  # a planted stretch lasts at least this long (s)
EXTEND_SPEED = 3.0  # m/s: while extending a contact (toe-off, heel strike, a retargeted foot sliding) it may move faster
HEIGHT_TOL = 0.01  # m: contact while the sole stays this close to the stretch's floor height


@dataclass
class KeyframeTable:
    times: np.ndarray  # (K,) seconds (frame / fps)
    frames: np.ndarray  # (K,) int, strictly increasing
    labels: tuple[str, ...]  # "" for uniform keyframes
    edited: np.ndarray  # (K,) bool
    sparse_scale: np.ndarray  # (K,) float
    flights: tuple[tuple[int, int], ...] = ()  # (takeoff frame, landing frame) found in the motion

    def __len__(self) -> int:
        return len(self.frames)

    def to_dict(self) -> dict:
        return {"times": self.times.tolist(), "frames": self.frames.tolist(), "labels": list(self.labels),
                "edited": self.edited.tolist(), "sparse_scale": self.sparse_scale.tolist(),
                "flights": [list(f) for f in self.flights]}

    @staticmethod
    def from_dict(raw: dict) -> "KeyframeTable":
        return KeyframeTable(times=np.asarray(raw["times"], float), frames=np.asarray(raw["frames"], int),
                             labels=tuple(raw["labels"]), edited=np.asarray(raw["edited"], bool),
                             sparse_scale=np.asarray(raw["sparse_scale"], float),
                             flights=tuple(tuple(f) for f in raw.get("flights", [])))


# ------------------------------------------------------------------------------------- contacts
@lru_cache(maxsize=1)
def _sole_points() -> tuple[np.ndarray, float]:
    """(P, 3) capsule end points of one foot's collision geoms in the ankle-roll body frame, and the
    capsule radius. Left and right feet are mirror images with the same points up to y's sign; both
    are read from the model to stay exact."""
    from pipeline.robot.g1 import build_model

    model = build_model(visual=False)
    out = {}
    radius = 0.0
    for side in ("left", "right"):
        body = model.body(f"{side}_ankle_roll_link").id
        pts = []
        for g in range(model.ngeom):
            if model.geom_bodyid[g] != body or model.geom_type[g] != mujoco.mjtGeom.mjGEOM_CAPSULE:
                continue
            axis = quat.rotate(model.geom_quat[g], np.array([0.0, 0.0, model.geom_size[g][1]]))
            pts += [model.geom_pos[g] + axis, model.geom_pos[g] - axis]
            radius = max(radius, float(model.geom_size[g][0]))
        out[side] = np.array(pts)
    return np.stack([out["left"], out["right"]]), radius


def sole_points_world(motion: Motion) -> np.ndarray:
    """(T, 2, P, 3) the feet's sole points (capsule ends) in the world, from the ankle bodies."""
    local, _ = _sole_points()
    ankles = [motion.body_index("left_ankle"), motion.body_index("right_ankle")]
    pos = motion.body_pos[:, ankles]  # (T, 2, 3)
    rot = motion.body_quat[:, ankles]  # (T, 2, 4)
    world = quat.rotate(rot[:, :, None, :], local[None]) + pos[:, :, None, :]
    return world


def foot_height_and_speed(motion: Motion) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2) height of each foot's lowest sole point (capsule surface) and that point's speed.

    The speed is the smaller of the backward and forward differences: a foot on its last frame on
    the ground (or first one back) is still on one side, which central differences would blur."""
    pts = sole_points_world(motion)
    _, radius = _sole_points()
    lowest = np.argmin(pts[..., 2], axis=-1)  # (T, 2)
    step = np.diff(pts, axis=0) / motion.dt  # (T-1, 2, P, 3)
    backward = np.concatenate([step[:1], step], axis=0)
    forward = np.concatenate([step, step[-1:]], axis=0)
    vel = np.where(np.linalg.norm(backward, axis=-1, keepdims=True) < np.linalg.norm(forward, axis=-1, keepdims=True),
                   backward, forward)
    take = lowest[..., None, None]
    height = np.take_along_axis(pts[..., 2], lowest[..., None], axis=-1)[..., 0] - radius
    speed = np.linalg.norm(np.take_along_axis(vel, np.broadcast_to(take, lowest.shape + (1, 3)), axis=2)[:, :, 0],
                           axis=-1)
    return height, speed


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of True."""
    padded = np.concatenate([[False], mask, [False]]).astype(int)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[0::2], edges[1::2]))


def detect_foot_contacts(motion: Motion) -> np.ndarray:
    """(T, 2) bool contact of (left, right) foot. A foot is planted where its lowest sole point is
    still for a while; the contact grows from there while the sole stays at that stretch's floor
    height (so toe-off and heel strike count, and a step onto a box has its own floor)."""
    height, speed = foot_height_and_speed(motion)
    t = motion.num_frames
    min_len = max(2, int(np.ceil(STILL_FRAMES_S * motion.fps)))
    contact = np.zeros((t, 2), bool)
    for foot in range(2):
        h, v = height[:, foot], speed[:, foot]
        for a, b in _runs(v < STILL_SPEED):
            if b - a < min_len:
                continue
            floor = float(np.median(h[a:b]))
            near = (np.abs(h - floor) < HEIGHT_TOL) & (v < EXTEND_SPEED)
            lo, hi = a, b
            while lo > 0 and near[lo - 1]:
                lo -= 1
            while hi < t and near[hi]:
                hi += 1
            contact[lo:hi, foot] = True
    return contact


def find_flights(contact: np.ndarray, fps: float, min_flight: float) -> list[tuple[int, int]]:
    """(takeoff, landing) frames around each stretch with no foot in contact, inside the clip."""
    airborne = ~contact.any(axis=1)
    min_len = max(1, int(round(min_flight * fps)))
    flights = []
    for a, b in _runs(airborne):
        if a == 0 or b >= len(airborne) or b - a < min_len:
            continue  # a clip starting or ending in the air has no takeoff/landing there
        flights.append((a - 1, b))
    return flights


# ------------------------------------------------------------------------------------- events
def _number(label: str, count: int, i: int) -> str:
    return label if count == 1 else f"{label}_{i + 1}"


def find_semantic_keyframes(motion: Motion, events: tuple[str, ...], min_flight: float
                            ) -> tuple[list[KeyframeSpec], list[tuple[int, int]]]:
    contact = detect_foot_contacts(motion)
    flights = find_flights(contact, motion.fps, min_flight)
    found: list[tuple[int, str]] = []
    n = len(flights)
    for i, (takeoff, landing) in enumerate(flights):
        if "takeoff" in events:
            found.append((takeoff, _number("takeoff", n, i)))
        if "apex" in events:
            found.append((takeoff + int(np.argmax(motion.root_pos[takeoff:landing + 1, 2])), _number("apex", n, i)))
        if "landing" in events:
            found.append((landing, _number("landing", n, i)))
    if "hit" in events:
        wrists = [motion.body_index("left_wrist"), motion.body_index("right_wrist")]
        speed = np.linalg.norm(motion.body_lin_vel[:, wrists], axis=-1).max(axis=1)
        edge = min(3, motion.num_frames // 4)  # finite differences are one-sided at the ends
        found.append((edge + int(np.argmax(speed[edge:motion.num_frames - edge])), "hit"))
    specs = [KeyframeSpec(float(frame) / motion.fps, label) for frame, label in sorted(found)]
    return specs, flights


def _default_events(task: TaskConfig) -> tuple[str, ...]:
    events = ["takeoff", "landing"]
    if task.edit.mode == "z_apex":
        events.insert(1, "apex")
    selectors = list(task.edit.keyframes) + list(task.large_scale_keyframes or ())
    for ev in ("apex", "hit"):
        if ev not in events and any(isinstance(s, str) and s.split("_")[0] == ev for s in selectors):
            events.append(ev)
    return tuple(events)


# ------------------------------------------------------------------------------------- table
def select_keyframes(motion: Motion, task: TaskConfig) -> KeyframeTable:
    """The task's keyframe table on `motion`; raises PipelineInputError (naming the task) for a
    keyframe beyond the motion's end or an edited keyframe that does not exist."""
    src = f"task {task.name}"
    kc = task.keyframes
    half_frame = 0.5 / motion.fps
    flights: list[tuple[int, int]] = []
    if kc.mode == "explicit":
        specs = list(kc.listed)
    else:
        events = kc.events if kc.events is not None else _default_events(task)
        semantic, flights = find_semantic_keyframes(motion, events, kc.min_flight)
        by_label = {s.label: s for s in semantic}
        for label, time in kc.overrides.items():
            by_label[label] = KeyframeSpec(time, label)
        semantic = sorted(by_label.values(), key=lambda s: s.time)
        semantic += [s for s in kc.extra]
        in_flight = [(a / motion.fps, b / motion.fps) for a, b in flights]
        uniform = []
        time = kc.first
        while time <= motion.duration - kc.end_margin + 1e-9:
            near = any(abs(time - s.time) < kc.min_gap for s in semantic)
            airborne = any(a < time < b for a, b in in_flight)
            if not near and not airborne:
                uniform.append(KeyframeSpec(round(time, 6), ""))
            time += kc.spacing
        specs = semantic + uniform

    for s in specs:
        if s.time > motion.duration + half_frame:
            raise PipelineInputError(src, "keyframes",
                                     f"keyframe at {s.time:.3f} s{' (' + s.label + ')' if s.label else ''} "
                                     f"is beyond the motion's end ({motion.duration:.3f} s)")
    # One keyframe per frame; a labelled one wins over a uniform one on the same frame.
    by_frame: dict[int, KeyframeSpec] = {}
    for s in sorted(specs, key=lambda s: (s.time, s.label == "")):
        frame = int(round(s.time * motion.fps))
        if frame not in by_frame or (not by_frame[frame].label and s.label):
            by_frame[frame] = s
    frames = np.array(sorted(by_frame), dtype=int)
    labels = tuple(by_frame[f].label for f in frames)
    times = frames / motion.fps

    def mask(selectors, field_name: str) -> np.ndarray:
        m = np.zeros(len(frames), bool)
        for sel in selectors:
            hits = np.array([_selector_hits(sel, t, lab, tol=half_frame) for t, lab in zip(times, labels)])
            if not hits.any():
                found = sorted({lab for lab in labels if lab})
                raise PipelineInputError(src, field_name,
                                         f"edited keyframe {sel!r} does not exist in this motion "
                                         f"(keyframes with labels {found})")
            m |= hits
        return m

    edited = mask(task.edit.keyframes or DEFAULT_EDITED[task.edit.mode], "edit.keyframes")
    if task.large_scale_keyframes is None:
        large = np.array([bool(lab) for lab in labels])
    else:
        large = mask(task.large_scale_keyframes, "sparse_scale.keyframes")
    scale = np.where(large, task.large_scale, 1.0)
    return KeyframeTable(times=times, frames=frames, labels=labels, edited=edited, sparse_scale=scale,
                         flights=tuple((int(a), int(b)) for a, b in flights))
