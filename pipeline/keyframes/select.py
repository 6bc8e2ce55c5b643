"""Keyframe selection: semantic keyframes found in the motion, uniform ones filling the rest.

Semantic events (beyond the paper, which hand-picks keyframes):
  * foot contacts from the tracked ankle bodies' poses (`motion/feet.py`): the lowest point of each
    foot's sole (the G1 foot capsules placed with the ankle's pose) and that point's speed;
  * takeoff = last frame with a foot in contact before a flight, landing = first frame after it
    (flight: no foot in contact for at least `min_flight` seconds; `motion/feet.py find_flights`), or
    the flights listed by hand (`keyframes.flights: [[takeoff, landing], ...]` in seconds); a task that
    declares its number of flights (`keyframes.flights: 3`) stops when another number is found;
  * apex = highest root inside a flight; hit = peak wrist speed.
Uniform keyframes every `spacing` seconds fill the rest, but never inside a flight: an unedited
target in mid-air would contradict every edited landing (the paper's far jump has none there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.config import DEFAULT_EDITED, KeyframeSpec, TaskConfig
from pipeline.keyframes.task_parsing import selector_hits
from pipeline.motion.feet import detect_foot_contacts, find_flights
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


# ------------------------------------------------------------------------------------- events
def _number(label: str, count: int, i: int) -> str:
    return label if count == 1 else f"{label}_{i + 1}"


def task_flights(motion: Motion, task: TaskConfig) -> list[tuple[int, int]]:
    """The (take-off, landing) frames of the task's flights on `motion`: listed by hand
    (`keyframes.flights` as times) or detected (`motion/feet.py`). A task that declares how many
    flights its clip holds (`keyframes.flights: N`) and is shown another number raises
    PipelineInputError naming the clip, what was found and how to list them by hand."""
    kc, fps = task.keyframes, motion.fps
    src, fld = f"task {task.name}", "keyframes.flights"
    if kc.flights:
        flights = []
        for i, (takeoff, landing) in enumerate(kc.flights):
            a, b = int(round(takeoff * fps)), int(round(landing * fps))
            if b > motion.num_frames - 1:
                raise PipelineInputError(src, f"{fld}[{i}]", f"lands at {landing} s, beyond the end of "
                                         f"{task.input} ({motion.duration:.2f} s)")
            if b - a < 1 or (flights and a <= flights[-1][1]):
                raise PipelineInputError(src, f"{fld}[{i}]", f"[{takeoff}, {landing}] s is not a flight of its own "
                                         f"at {fps:g} fps (frames {a}-{b})")
            flights.append((a, b))
        return flights
    flights = find_flights(detect_foot_contacts(motion), fps, kc.min_flight)
    if kc.flight_count is not None and len(flights) != kc.flight_count:
        listed = ", ".join(f"frames {a}-{b} ({a / fps:.2f}-{b / fps:.2f} s)" for a, b in flights) or "none"
        example = ", ".join(f"[{a / fps:.2f}, {b / fps:.2f}]" for a, b in flights[:kc.flight_count]) or "[1.20, 1.45]"
        raise PipelineInputError(
            src, fld,
            f"{task.input} should hold {kc.flight_count} flight(s) but {len(flights)} were found at {fps:g} fps "
            f"(take-off: the last frame with a foot down, landing: the first frame back): {listed}. Look at the "
            f"retargeted preview and list the {kc.flight_count} flight(s) by hand as [take-off, landing] times in "
            f"seconds, e.g. `keyframes: {{flights: [{example}]}}`, or change `keyframes.min_flight` (now "
            f"{kc.min_flight:g} s: shorter stretches with no foot down are not flights)")
    return flights


def find_semantic_keyframes(motion: Motion, events: tuple[str, ...], flights: list[tuple[int, int]]
                            ) -> list[KeyframeSpec]:
    """Takeoff, apex and landing of each flight (numbered when there are several), and the hit."""
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
    return [KeyframeSpec(float(frame) / motion.fps, label) for frame, label in sorted(found)]


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
        flights = task_flights(motion, task)
        semantic = find_semantic_keyframes(motion, events, flights)
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
            hits = np.array([selector_hits(sel, t, lab, tol=half_frame) for t, lab in zip(times, labels)])
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
