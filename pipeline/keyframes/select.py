"""Keyframe selection: semantic keyframes found in the motion, uniform ones filling the rest.

Semantic events (beyond the paper, which hand-picks keyframes):
  * foot contacts from the tracked ankle bodies' poses (`motion/feet.py`): the lowest point of each
    foot's sole (the G1 foot capsules placed with the ankle's pose) and that point's speed;
  * takeoff = last frame with a foot in contact before a flight, landing = first frame after it
    (flight: no foot in contact for at least `min_flight` seconds);
  * apex = highest root inside a flight; hit = peak wrist speed.
Uniform keyframes every `spacing` seconds fill the rest, but never inside a flight: an unedited
target in mid-air would contradict every edited landing (the paper's far jump has none there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.config import DEFAULT_EDITED, KeyframeSpec, TaskConfig, _selector_hits
from pipeline.motion.feet import detect_foot_contacts, runs
from pipeline.motion.motion import Motion


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


def find_flights(contact: np.ndarray, fps: float, min_flight: float) -> list[tuple[int, int]]:
    """(takeoff, landing) frames around each stretch with no foot in contact, inside the clip."""
    airborne = ~contact.any(axis=1)
    min_len = max(1, int(round(min_flight * fps)))
    flights = []
    for a, b in runs(airborne):
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
