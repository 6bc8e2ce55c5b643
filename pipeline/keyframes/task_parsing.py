"""Parsing and checking a task's declaration (`params.yaml` `tasks.<name>`) into `TaskConfig`
(pipeline/keyframes/config.py): every field checked before any work, one clear error naming the task
and the field."""

from __future__ import annotations

import math
import re

from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.config import (AUTO_EVENTS, CUMULATIVE_MODES, DEFAULT_EDITED, EDIT_MODES, TERRAIN_KINDS, LABEL_PATTERN,
                                       ClipWindow, EditConfig, KeyframesConfig, KeyframeSpec, PsiConfig, Range, Selector,
                                       TaskConfig, TerrainConfig, _err, label_matches)
from pipeline.priors.push_prior import PushPriorConfig


def _number(name: str, fld: str, value, *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _err(name, fld, f"must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise _err(name, fld, f"must be > 0, got {value}")
    if nonneg and value < 0:
        raise _err(name, fld, f"must be >= 0, got {value}")
    return float(value)


def _check_keys(name: str, fld: str, raw: dict, allowed: set[str]) -> None:
    if not isinstance(raw, dict):
        raise _err(name, fld, f"must be a mapping, got {type(raw).__name__}")
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise _err(name, fld, f"unknown key(s) {unknown}; allowed {sorted(allowed)}")


def _label(name: str, fld: str, value) -> str:
    if value is None or value == "":
        return ""
    if not isinstance(value, str) or not LABEL_PATTERN.match(value):
        raise _err(name, fld, f"label must be lower-case letters/digits with an optional _N, got {value!r}")
    return value


def _keyframe_spec(name: str, fld: str, raw) -> KeyframeSpec:
    if isinstance(raw, (int, float)) and not isinstance(raw, bool):
        raw = {"time": raw}
    _check_keys(name, fld, raw, {"time", "label"})
    if "time" not in raw:
        raise _err(name, fld, "needs a time (seconds)")
    time = _number(name, f"{fld}.time", raw["time"], nonneg=True)
    return KeyframeSpec(time, _label(name, f"{fld}.label", raw.get("label")))


def _parse_keyframes(name: str, raw) -> KeyframesConfig:
    if raw is None or raw == "auto":
        return KeyframesConfig()
    if isinstance(raw, list):
        if not raw:
            raise _err(name, "keyframes", "an explicit list needs at least one keyframe")
        specs = tuple(_keyframe_spec(name, f"keyframes[{i}]", k) for i, k in enumerate(raw))
        times = [s.time for s in specs]
        if any(b <= a for a, b in zip(times, times[1:])):
            raise _err(name, "keyframes", f"times must be strictly increasing, got {times}")
        labels = [s.label for s in specs if s.label]
        if len(labels) != len(set(labels)):
            raise _err(name, "keyframes", f"labels must be unique (number them: landing_1...), got {labels}")
        return KeyframesConfig(mode="explicit", listed=specs)
    if isinstance(raw, str):
        raise _err(name, "keyframes", f"must be 'auto', a list of {{time, label}} or a mapping, got {raw!r}")
    _check_keys(name, "keyframes", raw, {"mode", "spacing", "first", "end_margin", "min_gap", "events",
                                          "overrides", "extra", "min_flight", "flights"})
    if raw.get("mode", "auto") != "auto":
        raise _err(name, "keyframes.mode", f"only 'auto' takes options (a list is explicit), got {raw.get('mode')!r}")
    d = KeyframesConfig()
    events = raw.get("events")
    if events is not None:
        if not isinstance(events, list) or any(e not in AUTO_EVENTS for e in events):
            raise _err(name, "keyframes.events", f"must be a list from {list(AUTO_EVENTS)}, got {events!r}")
        events = tuple(events)
    overrides = raw.get("overrides") or {}
    _check_keys(name, "keyframes.overrides", overrides, set(overrides))
    parsed_overrides = {}
    for label, time in overrides.items():
        _label(name, f"keyframes.overrides.{label}", label)
        parsed_overrides[label] = _number(name, f"keyframes.overrides.{label}", time, nonneg=True)
    extra = raw.get("extra") or []
    if not isinstance(extra, list):
        raise _err(name, "keyframes.extra", "must be a list of {time, label}")
    flight_count, flights = _parse_flights(name, raw.get("flights"))
    return KeyframesConfig(
        mode="auto",
        spacing=_number(name, "keyframes.spacing", raw.get("spacing", d.spacing), positive=True),
        first=_number(name, "keyframes.first", raw.get("first", d.first), nonneg=True),
        end_margin=_number(name, "keyframes.end_margin", raw.get("end_margin", d.end_margin), nonneg=True),
        min_gap=_number(name, "keyframes.min_gap", raw.get("min_gap", d.min_gap), nonneg=True),
        events=events,
        overrides=parsed_overrides,
        extra=tuple(_keyframe_spec(name, f"keyframes.extra[{i}]", k) for i, k in enumerate(extra)),
        min_flight=_number(name, "keyframes.min_flight", raw.get("min_flight", d.min_flight), positive=True),
        flight_count=flight_count,
        flights=flights,
    )


def _parse_flights(name: str, raw) -> tuple[int | None, tuple[tuple[float, float], ...]]:
    """`keyframes.flights`: how many flights the clip holds (a count), or the flights themselves as
    [take-off, landing] times in seconds, in order (listed by hand: nothing is detected)."""
    fld = "keyframes.flights"
    if raw is None:
        return None, ()
    if isinstance(raw, int) and not isinstance(raw, bool):
        if raw < 0:
            raise _err(name, fld, f"a count of flights must be >= 0, got {raw}")
        return raw, ()
    if not isinstance(raw, list) or not raw:
        raise _err(name, fld, "must be the number of flights the clip holds (e.g. 3) or a non-empty list of "
                              f"[take-off, landing] times in seconds, got {raw!r}")
    flights: list[tuple[float, float]] = []
    for i, pair in enumerate(raw):
        if not isinstance(pair, (list, tuple)) or len(pair) != 2:
            raise _err(name, f"{fld}[{i}]", f"must be [take-off, landing] in seconds, got {pair!r}")
        takeoff = _number(name, f"{fld}[{i}]", pair[0], nonneg=True)
        landing = _number(name, f"{fld}[{i}]", pair[1], nonneg=True)
        if landing <= takeoff:
            raise _err(name, f"{fld}[{i}]", f"the landing ({landing} s) must come after the take-off ({takeoff} s)")
        if flights and takeoff <= flights[-1][1]:
            raise _err(name, f"{fld}[{i}]", f"takes off at {takeoff} s, before the flight before it has landed "
                                            f"({flights[-1][1]} s): list the flights in order, one after the other")
        flights.append((takeoff, landing))
    return len(flights), tuple(flights)


def _selectors(name: str, fld: str, raw) -> tuple[Selector, ...]:
    if not isinstance(raw, list) or not raw:
        raise _err(name, fld, f"must be a non-empty list of labels or times, got {raw!r}")
    out: list[Selector] = []
    for i, s in enumerate(raw):
        if isinstance(s, str):
            out.append(_label(name, f"{fld}[{i}]", s))
        else:
            out.append(_number(name, f"{fld}[{i}]", s, nonneg=True))
    return tuple(out)


def _parse_edit(name: str, raw) -> EditConfig:
    if raw is None:
        raise _err(name, "edit", f"missing; one of {list(EDIT_MODES)} or {{mode, keyframes, sign}}")
    if isinstance(raw, str):
        raw = {"mode": raw}
    _check_keys(name, "edit", raw, {"mode", "keyframes", "sign"})
    mode = raw.get("mode")
    if mode not in EDIT_MODES:
        raise _err(name, "edit.mode", f"unknown edit axis {mode!r}; one of {list(EDIT_MODES)}")
    keyframes = raw.get("keyframes")
    selectors = DEFAULT_EDITED[mode] if keyframes is None else _selectors(name, "edit.keyframes", keyframes)
    sign = _number(name, "edit.sign", raw.get("sign", 1.0))
    if sign not in (1.0, -1.0):
        raise _err(name, "edit.sign", f"must be 1 or -1, got {sign}")
    return EditConfig(mode=mode, keyframes=selectors, sign=sign)


def _ranges(name: str, fld: str, raw, *, allow_empty: bool) -> tuple[Range, ...]:
    if raw is None:
        raw = []
    if not isinstance(raw, list):
        raise _err(name, fld, f"must be a list of [lo, hi], got {raw!r}")
    if isinstance(raw, list) and len(raw) == 2 and all(isinstance(v, (int, float)) for v in raw):
        raw = [raw]  # one range written flat: [lo, hi]
    if not raw and not allow_empty:
        raise _err(name, fld, "is empty: needs at least one [lo, hi]")
    out = []
    for i, r in enumerate(raw):
        if not isinstance(r, (list, tuple)) or len(r) != 2:
            raise _err(name, f"{fld}[{i}]", f"must be [lo, hi], got {r!r}")
        lo = _number(name, f"{fld}[{i}]", r[0])
        hi = _number(name, f"{fld}[{i}]", r[1])
        if hi < lo:
            raise _err(name, f"{fld}[{i}]", f"inverted range [{lo}, {hi}]")
        if hi == lo:
            raise _err(name, f"{fld}[{i}]", f"empty range [{lo}, {hi}]")
        out.append((lo, hi))
    return tuple(out)


def merge_ranges(ranges) -> tuple[Range, ...]:
    """Sorted union of [lo, hi] ranges (touching ones merged)."""
    merged: list[list[float]] = []
    for lo, hi in sorted(ranges):
        if merged and lo <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    return tuple((lo, hi) for lo, hi in merged)


def _parse_psi(name: str, raw) -> PsiConfig:
    if raw is None:
        raise _err(name, "psi", "missing; needs raw and ranges (easy, hard and/or train)")
    _check_keys(name, "psi", raw, {"raw", "easy", "hard", "train", "meaning"})
    if "raw" not in raw:
        raise _err(name, "psi.raw", "missing: the unedited clip's task variable")
    psi_raw = _number(name, "psi.raw", raw["raw"])
    if not any(k in raw for k in ("easy", "hard", "train")):
        raise _err(name, "psi", "needs at least one of easy, hard, train ranges")
    train_given = "train" in raw
    train = _ranges(name, "psi.train", raw.get("train"), allow_empty=not train_given)
    easy = _ranges(name, "psi.easy", raw.get("easy"), allow_empty="easy" not in raw)
    hard = _ranges(name, "psi.hard", raw.get("hard"), allow_empty="hard" not in raw)
    if not easy and not hard:
        easy = train  # only train given: everything counts as easy for the figure / evaluation
    if not train:
        train = merge_ranges(easy + hard)
    meaning = raw.get("meaning", "")
    if not isinstance(meaning, str):
        raise _err(name, "psi.meaning", f"must be text, got {meaning!r}")
    return PsiConfig(raw=psi_raw, easy=easy, hard=hard, train=train, meaning=meaning)


def _parse_terrain(name: str, raw) -> TerrainConfig:
    if raw is None:
        return TerrainConfig()
    if isinstance(raw, str):
        raw = {"kind": raw}
    _check_keys(name, "terrain", raw, {"kind", "margin", "depth", "height", "anchors"})
    kind = raw.get("kind", "flat")
    if kind not in TERRAIN_KINDS:
        raise _err(name, "terrain.kind", f"unknown terrain {kind!r}; one of {list(TERRAIN_KINDS)}")
    d = TerrainConfig()
    height = raw.get("height", d.height)
    if height not in ("reference", "psi"):
        raise _err(name, "terrain.height", f"must be 'reference' or 'psi', got {height!r}")
    anchors = raw.get("anchors") or {}
    if not isinstance(anchors, dict):
        raise _err(name, "terrain.anchors", "must be a mapping")
    return TerrainConfig(
        kind=kind,
        margin=_number(name, "terrain.margin", raw.get("margin", d.margin), nonneg=True),
        depth=_number(name, "terrain.depth", raw.get("depth", d.depth), positive=True),
        height=height,
        anchors=dict(anchors),
    )


_TASK_KEYS = {"input", "keyframes", "edit", "psi", "sparse_scale", "terrain", "num_samples", "push_prior", "clip"}


def _parse_clip(name: str, raw) -> ClipWindow:
    if raw is None:
        return ClipWindow()
    _check_keys(name, "clip", raw, {"start_s", "end_s", "lead_in_s", "handoff_after_landing_s"})
    start = _number(name, "clip.start_s", raw.get("start_s", 0.0), nonneg=True)
    end = raw.get("end_s")
    if end is not None:
        end = _number(name, "clip.end_s", end, positive=True)
        if end <= start:
            raise _err(name, "clip.end_s", f"must be after clip.start_s ({start} s), got {end}")
    handoff = raw.get("handoff_after_landing_s")
    if handoff is not None:
        handoff = _number(name, "clip.handoff_after_landing_s", handoff, nonneg=True)
    return ClipWindow(start, end, _number(name, "clip.lead_in_s", raw.get("lead_in_s", 0.0), nonneg=True), handoff)


def _parse_push_prior(name: str, raw, edit: EditConfig) -> PushPriorConfig:
    if raw is None:
        return PushPriorConfig()
    if isinstance(raw, bool):
        raw = {"enabled": raw}
    _check_keys(name, "push_prior", raw, {"enabled", "iterations", "population", "seed", "knots", "land_by_slack_s"})
    enabled = raw.get("enabled", False)
    if not isinstance(enabled, bool):
        raise _err(name, "push_prior.enabled", f"must be true or false, got {enabled!r}")
    counts = {}
    for key, low in (("iterations", 1), ("population", 2), ("seed", 0), ("knots", 2)):
        value = raw.get(key, getattr(PushPriorConfig, key))
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise _err(name, f"push_prior.{key}", f"must be an integer >= {low}, got {value!r}")
        counts[key] = value
    slack = raw.get("land_by_slack_s", PushPriorConfig.land_by_slack_s)
    if isinstance(slack, bool) or not isinstance(slack, (int, float)) or not 0.0 <= slack <= 0.5:
        raise _err(name, "push_prior.land_by_slack_s", f"must be seconds in [0, 0.5], got {slack!r}")
    if enabled and (edit.mode != "x" or edit.sign != 1.0):
        raise _err(name, "push_prior.enabled", f"a push prior lengthens a jump along +x (edit mode x), not {edit.mode!r}")
    return PushPriorConfig(enabled=enabled, land_by_slack_s=float(slack), **counts)


def parse_task(name: str, raw: dict) -> TaskConfig:
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_\-]+", name):
        raise PipelineInputError(f"task {name}", None, "task names are letters, digits, _ and -")
    _check_keys(name, "", raw, _TASK_KEYS)
    inp = raw.get("input")
    if not isinstance(inp, str) or not inp:
        raise _err(name, "input", f"must be a path to the input clip, got {inp!r}")
    keyframes = _parse_keyframes(name, raw.get("keyframes"))
    edit = _parse_edit(name, raw.get("edit"))
    psi = _parse_psi(name, raw.get("psi"))
    terrain = _parse_terrain(name, raw.get("terrain"))
    if terrain.kind == "step" and edit.mode != "z_hold":
        raise _err(name, "terrain.kind", f"a step follows a z_hold edit, not {edit.mode!r}")
    if terrain.kind == "gap" and edit.mode not in CUMULATIVE_MODES:
        raise _err(name, "terrain.kind", f"a gap follows a horizontal edit (x, y, heading), not {edit.mode!r}")

    scale = raw.get("sparse_scale") or {}
    _check_keys(name, "sparse_scale", scale, {"large", "keyframes"})
    large = _number(name, "sparse_scale.large", scale.get("large", 50.0), positive=True)
    large_kf = scale.get("keyframes", "semantic")
    large_sel = None if large_kf == "semantic" else _selectors(name, "sparse_scale.keyframes", large_kf)

    push_prior = _parse_push_prior(name, raw.get("push_prior"), edit)
    clip = _parse_clip(name, raw.get("clip"))

    num = raw.get("num_samples", 64)
    if isinstance(num, bool) or not isinstance(num, int) or num < 1:
        raise _err(name, "num_samples", f"must be an integer >= 1, got {num!r}")

    if keyframes.mode == "explicit":  # every selector must name a listed keyframe
        for fld, sels in (("edit.keyframes", edit.keyframes), ("sparse_scale.keyframes", large_sel or ())):
            for s in sels:
                if not any(selector_hits(s, k.time, k.label) for k in keyframes.listed):
                    raise _err(name, fld, f"edited keyframe {s!r} does not exist in the keyframe list")
    return TaskConfig(name=name, input=inp, edit=edit, psi=psi, keyframes=keyframes, large_scale=large,
                      large_scale_keyframes=large_sel, terrain=terrain, num_samples=num,
                      push_prior=push_prior, clip=clip)


def selector_hits(selector: Selector, time: float, label: str, tol: float = 1e-6) -> bool:
    if isinstance(selector, str):
        return label_matches(selector, label)
    return abs(time - selector) <= tol


def load_tasks(raw_tasks: dict) -> dict[str, TaskConfig]:
    """All tasks of `params.yaml` `tasks:`, each validated; the first bad one raises."""
    if not isinstance(raw_tasks, dict) or not raw_tasks:
        raise PipelineInputError("params.yaml", "tasks", "must be a non-empty mapping of task name -> task")
    return {name: TaskConfig.from_dict(name, raw) for name, raw in raw_tasks.items()}
