"""A push prior: a zero action that already jumps each sample's gap, open loop.

The feedforward zero action (`envs/feedforward.py`) replays the reference's own torques. On the
shared far jump it lands at ψ 0.22 m where the clip jumps 1.1 m and the task asks 0.2–2.0 m, so a
policy has to learn the whole push-off a longer gap needs from exploration noise, and 420 CPU
iterations never taught one past 1.4 m (benchmarks/RESULTS.md). The prior gives the zero action
that push, scaled to each sample's ψ:

    joint targets = feedforward(frame) + w(ψ) · push(frame) + action_scale · action

* `push` is the open-loop offset curve that jumps furthest from the reference's state 0.5 s before
  the take-off while it still touches down by the reference's landing time and passes the env's fall
  checks (`priors/open_loop.py: cross_entropy_search`), faded to zero over the 0.2 s after its
  touch-down: standing up from the landing stays the policy's job.
* `w(ψ)` is measured, not assumed: the push is rolled out at w = 0, 0.025, …, 1.2, each rollout's
  jump turned into the ψ it reaches, and w(ψ) is the piecewise-linear inverse over the rollouts
  that pass the fall checks (kept where ψ grows). A jump reaches ψ where its rear ankle lands as far
  past the reference's landing as the edit moves it (ψ − ψ_raw): the gap and the keyframes sit in
  the motion's frame, so how far the feet flew from wherever the robot took off is not what counts.
  (Measured by the feet's travel instead, the far jump's priors took off 0.15–0.21 m behind the
  reference and landed every pushed ψ at the gap's far edge, 0.15 m short of its target.) Outside
  the measured ψ it holds the end values, so gaps shorter than the zero action's own jump get no push
  and gaps past the furthest one get the largest that passed.

The env adds it (`TrackingEnv._action_offset`), the exported graph adds it from the observed ψ
(`export/onnx_export.py`), and the DVC stage `push_prior` writes it per task when the task asks for
one (`push_prior: {enabled: true}` in params.yaml).
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.common.atomic import atomic_file, write_text_atomic
from pipeline.common.errors import PipelineInputError
from pipeline.common.npz import savez_reproducible

LEAD_S = 0.5          # the window starts this long before the take-off (learn_cpu's segment does too)
AFTER_LANDING_S = 0.6  # and ends this long after the reference's landing
FADE_S = 0.2           # the push fades to zero over this long after its touch-down
WEIGHT_STEP, WEIGHT_MAX = 0.025, 1.2
FILE_JSON, FILE_ARRAYS = "push_prior.json", "push_prior.npz"


@dataclass(frozen=True)
class PushPriorConfig:
    """`tasks.<name>.push_prior` in params.yaml. The search costs iterations × population rollouts of
    ~1.4 s each (40 × 256: about 1–4 minutes on 2 cores). `knots`: the push curves' resolution in time,
    knots evenly spaced over the window (about 1.4 s)."""

    enabled: bool = False
    iterations: int = 40
    population: int = 256
    seed: int = 0
    # 12: a knot every 0.13 s. On learn_cpu's far-jump segment 12 reach ψ 1.58 m within the fall checks (read
    # by the feet's travel, which overstates it by 0.15–0.2 m), 20 reach 1.77 m read at the landing, and
    # every learn_cpu run over the 0.9 goal trained on a 20-knot prior, which learn_cpu searches by default
    # (benchmarks/RESULTS.md, commits 2184b6a, ff6fc64 and b822369). 20 is not the default here: with a tiny search on the
    # bundled sample its env landings strayed up to 0.12 m from the prior's (tests/test_push_prior.py; 12 knots:
    # 0.07). The sample's episodes start 35 frames before the push's window and reach it off the reference's state,
    # which the finer push is more sensitive to; where the window starts the episode (learn_cpu) they agree to 0.03 m.
    knots: int = 12
    # The search's touch-down may be this much later than the reference's landing (s).
    land_by_slack_s: float = 0.04
    # Opt-in: the search's touch-down must also be within these margins of the reference's posture at its
    # landing keyframe: feet no further ahead of the pelvis (m), trunk leaning forward no less (gravity's x in
    # the pelvis frame), pitching backward no faster (rad/s). See open_loop.LandingPosture. Off: on learn_cpu's
    # 2.3 s far-jump segment the policy trained on such a prior read 0.000 against 0.094 (benchmarks/RESULTS.md,
    # commit 0a98857); only the push at w = 1 is searched, and the scaled ones still land in any posture.
    reference_posture: bool = False
    posture_feet_ahead_margin_m: float = 0.1
    posture_lean_margin: float = 0.3
    posture_pitch_rate_margin: float = 0.6


@dataclass
class PushPrior:
    joint_offsets: np.ndarray   # (T, J) rad at w = 1, per frame of the task's motion, robot joint order
    psi_anchors: np.ndarray     # (A,) increasing ψ (m) ...
    weight_anchors: np.ndarray  # (A,) ... and the push weight w that reaches it, non-decreasing
    joint_names: tuple[str, ...]
    summary: dict = field(default_factory=dict)

    def weight(self, psi) -> np.ndarray:
        """w(ψ): piecewise linear between the anchors, held at the end values outside them."""
        return np.interp(np.asarray(psi, dtype=np.float64), self.psi_anchors, self.weight_anchors)


def flight_frames(data) -> tuple[int, int]:
    """The first take-off keyframe and the first landing keyframe after it (frames of `data.motion`)."""
    labels = list(data.keyframe_labels)
    frames = [int(f) for f in data.keyframe_frames]
    takeoff = next((f for f, label in zip(frames, labels) if label.startswith("takeoff")), None)
    landing = next((f for f, label in zip(frames, labels) if label.startswith("landing") and takeoff is not None
                    and f > takeoff), None)
    if takeoff is None or landing is None:
        raise PipelineInputError(f"task {data.task}", "push_prior",
                                 f"needs a take-off and a later landing keyframe, the keyframes are {labels}")
    return takeoff, landing


def monotone_anchors(psi: np.ndarray, weight: np.ndarray, min_step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """(ψ, w) pairs in order of w -> the pairs where ψ grows by at least `min_step` over the last kept:
    a table w(ψ) can be read from (the smallest w that reaches each ψ)."""
    kept_psi, kept_w = [], []
    for p, w in zip(psi, weight):
        if not kept_psi or p >= kept_psi[-1] + min_step:
            kept_psi.append(float(p))
            kept_w.append(float(w))
    return np.array(kept_psi), np.array(kept_w)


def build_push_prior(data, cfg: PushPriorConfig, robot=None, log=print, physics: str | None = None) -> PushPrior:
    """Searches the push for `data` (D_edit of a task whose edit moves the landing along x) and measures w(ψ).
    `log`: where progress lines go (None: nowhere). `physics`: the env's physics preset (None: robot.yaml's default)."""
    from pipeline.priors.open_loop import OpenLoopJumps, cross_entropy_search
    from pipeline.robot.g1 import load_robot_config

    robot = robot or load_robot_config()
    log = log or (lambda line: None)
    motion = data.motion
    takeoff, landing = flight_frames(data)
    fps = motion.fps
    start = max(0, takeoff - int(round(LEAD_S * fps)))
    steps = min(motion.num_frames - 1 - start, landing - start + int(round(AFTER_LANDING_S * fps)))
    jumps = OpenLoopJumps(motion, robot, start, steps, knots=cfg.knots, physics=physics)
    reference_landing_x = float(jumps.segment.body_pos[landing, jumps.ankles, 0].min())

    def psi_of(jump) -> float:  # the edit moves the landing by ψ − ψ_raw, so the rear ankle lands that much further
        return float(data.psi_raw + jump.landing_x - reference_landing_x)

    land_by = (landing - start) / fps + cfg.land_by_slack_s
    allowance = jumps.reference_capture_outside(landing)
    posture = (jumps.reference_posture(landing, cfg.posture_feet_ahead_margin_m, cfg.posture_lean_margin,
                                       cfg.posture_pitch_rate_margin) if cfg.reference_posture else None)
    began = time.time()
    log(f"push prior for {data.task}: frames {start}..{start + steps} (take-off {takeoff}, landing {landing}), "
        f"{cfg.iterations} iterations of {cfg.population} rollouts")
    offsets, jump = cross_entropy_search(jumps, land_by, allowance, cfg.iterations, cfg.population,
                                         np.random.default_rng(cfg.seed), fall_checks=True, log=log,
                                         landable_only=True, distance="landing", posture=posture)
    if jump is None:
        raise PipelineInputError(f"task {data.task}", "push_prior",
                                 f"none of the search's {cfg.iterations} x {cfg.population} rollouts landed within "
                                 f"the env's fall checks (raise push_prior.iterations or .population)")
    curve = jumps.curves(offsets[None])[0]  # (steps, J): control step k aims at frame start + k + 1
    # The fade starts after the control step the touch-down falls in (it aims at frame start + k + 1), so the
    # table at w = 1 replays the searched flight exactly.
    touch = start + int(round(jump.landing_s / jumps.dt)) // jumps.substeps + 1
    frames = start + 1 + np.arange(steps)
    fade = np.clip(1.0 - (frames - touch) / (FADE_S * fps), 0.0, 1.0)
    table = np.zeros((motion.num_frames, curve.shape[1]))
    table[frames] = curve * fade[:, None]

    weights = np.round(np.arange(0.0, WEIGHT_MAX + 1e-9, WEIGHT_STEP), 6)
    faded = table[frames]
    measured = jumps.jumps_of_curves(weights[:, None, None] * faded[None])
    passes = [j is not None and j.fall_check_excess == 0.0 for j in measured]
    passing = [(psi_of(j), w) for w, j, ok in zip(weights, measured, passes) if ok]
    if not passing:
        raise PipelineInputError(f"task {data.task}", "push_prior", "no scaled push passes the env's fall checks")
    psi_anchors, weight_anchors = monotone_anchors(*map(np.array, zip(*passing)))
    zero = measured[0]
    summary = {
        "task": data.task, "window_frames": [start, start + steps], "takeoff_frame": takeoff, "landing_frame": landing,
        "touchdown_frame": touch,
        "psi_raw": float(data.psi_raw), "psi_reached": psi_of(jump), "jump": str(jump),
        "zero_action_psi": psi_of(zero) if zero is not None else None,
        "max_abs_offset_rad": float(np.abs(table).max()),
        "config": {"iterations": cfg.iterations, "population": cfg.population, "seed": cfg.seed, "knots": cfg.knots,
                   "land_by_slack_s": cfg.land_by_slack_s},
        "landing_posture_limits": None if posture is None else dataclasses.asdict(posture),
        "measured": [{"w": float(w), "psi": psi_of(j) if j else None, "passes_fall_checks": ok}
                     for w, j, ok in zip(weights, measured, passes)],
    }
    # The search time is logged, not stored: push_prior.json holds only what the inputs determine.
    log(f"push prior for {data.task}: ψ {psi_of(jump):.2f} m at w = 1 ({jump}); w(ψ) over "
        f"ψ {psi_anchors[0]:.2f}–{psi_anchors[-1]:.2f} m from {len(psi_anchors)} anchors, "
        f"{time.time() - began:.0f} s")
    return PushPrior(table, psi_anchors, weight_anchors, tuple(robot.joint_names), summary)


def write_push_prior(out_dir: str | Path, prior: PushPrior | None) -> None:
    """`push_prior.json` (always: whether the task has a prior, its anchors and summary) and, with a
    prior, `push_prior.npz` (the per-frame table). Each file is written atomically."""
    out_dir = Path(out_dir)
    doc = {"enabled": prior is not None}
    if prior is not None:
        with atomic_file(out_dir / FILE_ARRAYS) as f:
            savez_reproducible(f, joint_offsets=prior.joint_offsets, psi_anchors=prior.psi_anchors,
                               weight_anchors=prior.weight_anchors, joint_names=np.array(prior.joint_names))
        doc.update({"psi_anchors": prior.psi_anchors.tolist(), "weight_anchors": prior.weight_anchors.tolist(),
                    "summary": prior.summary})
    write_text_atomic(out_dir / FILE_JSON, json.dumps(doc, indent=1))


def load_push_prior(out_dir: str | Path, num_frames: int, joint_names) -> PushPrior | None:
    """The prior `write_push_prior` wrote (None when its task has none), checked against the motion's
    frame count and the robot's joints."""
    out_dir = Path(out_dir)
    path = out_dir / FILE_JSON
    if not path.is_file():
        raise PipelineInputError(path, None, "missing (run the push_prior stage first)")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise PipelineInputError(path, None, f"not JSON ({e})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("enabled"), bool):
        raise PipelineInputError(path, "enabled", "must be true or false")
    if not doc["enabled"]:
        return None
    arrays_path = out_dir / FILE_ARRAYS
    if not arrays_path.is_file():
        raise PipelineInputError(arrays_path, None, "missing, though push_prior.json says enabled")
    with np.load(arrays_path) as z:
        for key in ("joint_offsets", "psi_anchors", "weight_anchors", "joint_names"):
            if key not in z.files:
                raise PipelineInputError(arrays_path, key, "missing")
        table, psi, w = (np.asarray(z[k], dtype=np.float64) for k in ("joint_offsets", "psi_anchors", "weight_anchors"))
        names = tuple(str(n) for n in z["joint_names"])
    if names != tuple(joint_names):
        raise PipelineInputError(arrays_path, "joint_names", f"{len(names)} joints that are not the robot's {len(joint_names)}")
    if table.shape != (num_frames, len(joint_names)) or not np.all(np.isfinite(table)):
        raise PipelineInputError(arrays_path, "joint_offsets",
                                 f"shape {table.shape}, needs finite ({num_frames}, {len(joint_names)}) for this motion")
    if psi.ndim != 1 or psi.shape != w.shape or psi.size == 0 or not np.all(np.isfinite(psi)) \
            or not np.all(np.isfinite(w)) or np.any(np.diff(psi) <= 0) or np.any(np.diff(w) < 0):
        raise PipelineInputError(arrays_path, "psi_anchors",
                                 "needs increasing finite ψ anchors with non-decreasing weights of the same length")
    return PushPrior(table, psi, w, names, doc.get("summary", {}))
