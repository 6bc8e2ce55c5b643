"""Open-loop jumps of the G1: the zero action's joint targets plus offset curves, rolled out in MuJoCo C.

A window of a reference motion (from frame `start`, `steps` control steps) is replayed from the
reference's state at `start`, on flat ground, with the feedforward zero action
(`envs/feedforward.py`) plus an offset curve per joint. The curves the search moves are piecewise
linear in time, on five channels shared by both sides of the body (hip pitch, knee, ankle pitch,
shoulder pitch, elbow): a push-off and an arm swing, the degrees of freedom a longer jump needs.

Each rollout is measured over its first flight of at least 0.1 s (`Jump`): how far the feet travel
(the rear ankle at touch-down minus the front ankle at take-off) and where the rear ankle lands,
its timing, the trunk's tilt and pitch rate at touch-down, the pelvis's height in the air,
where the capture point lies against the soles, the landing posture (feet ahead of the pelvis, trunk
lean), and whether the training env's fall checks (`envs/config.py: TerminationConfig`, relative to the
reference) hold until 0.1 s after the touch-down. `cross_entropy_search` finds the offsets that jump
furthest within those limits.

Used by `priors/push_prior.py` (the push the env adds to the zero action) and by
`benchmarks/jump_ceiling.py` (how far the robot can jump at all).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from pipeline.common import quat
from pipeline.motion.feet import find_flights

# The channels the search moves, each the same offset on both sides of the body.
CHANNELS = (("left_hip_pitch_joint", "right_hip_pitch_joint"), ("left_knee_joint", "right_knee_joint"),
            ("left_ankle_pitch_joint", "right_ankle_pitch_joint"),
            ("left_shoulder_pitch_joint", "right_shoulder_pitch_joint"), ("left_elbow_joint", "right_elbow_joint"))
KNOTS = 12  # the default resolution in time (push_prior.py: PushPriorConfig.knots, jump_ceiling.py --knots)
MIN_FLIGHT_S = 0.1
MAX_TILT, MAX_PITCH_RATE, MIN_FLIGHT_PELVIS_M = 0.6, 3.0, 0.5
DOWN = np.array([0.0, 0.0, -1.0])
SOLE_X = (-0.05, 0.13)      # heel and toe about the ankle (the G1's sole capsules, robots/g1/vendor/xmls)


@dataclass
class Jump:
    feet_m: float           # rear ankle at touch-down minus front ankle at take-off
    landing_x: float        # rear ankle at touch-down, x in the motion's frame (where the terrain and keyframes are)
    pelvis_m: float         # the pelvis's horizontal travel, take-off to touch-down
    takeoff_s: float        # from the window's start
    landing_s: float
    tilt: float             # |gravity_xy| in the pelvis frame at touch-down
    pitch_rate: float       # rad/s at touch-down
    lowest_pelvis_m: float  # in the air
    apex_pelvis_m: float
    capture_outside_m: float  # how far the capture point lies outside the soles at touch-down (0: inside)
    fall_check_excess: float  # the training env's fall checks, worst excess until 0.1 s after touch-down (0: passed)
    feet_ahead_m: float = 0.0  # rear ankle ahead of the pelvis at touch-down (x)
    lean: float = 0.0          # gravity's x in the pelvis frame at touch-down: + leaning forward

    def penalty(self, land_by_s: float, capture_allowance_m: float, fall_checks: bool = False,
                posture: LandingPosture | None = None) -> float:
        return ((5.0 * posture.excess(self) if posture is not None else 0.0)
                + 2.0 * max(0.0, self.tilt - MAX_TILT)
                + (5.0 * self.fall_check_excess if fall_checks else 0.0)
                + 0.2 * max(0.0, abs(self.pitch_rate) - MAX_PITCH_RATE)
                + 5.0 * max(0.0, MIN_FLIGHT_PELVIS_M - self.lowest_pelvis_m)
                + 5.0 * max(0.0, self.capture_outside_m - capture_allowance_m)
                + 10.0 * max(0.0, self.landing_s - land_by_s))

    def landable(self, land_by_s: float, capture_allowance_m: float, fall_checks: bool = False,
                 posture: LandingPosture | None = None) -> bool:
        return self.penalty(land_by_s, capture_allowance_m, fall_checks, posture) == 0.0

    def __str__(self) -> str:
        return (f"feet {self.feet_m:.2f} m (pelvis {self.pelvis_m:.2f} m), take-off {self.takeoff_s:.2f} s, "
                f"touch-down {self.landing_s:.2f} s, tilt {self.tilt:.2f}, pitch rate {self.pitch_rate:+.1f} rad/s, "
                f"pelvis {self.lowest_pelvis_m:.2f}-{self.apex_pelvis_m:.2f} m in the air, "
                f"feet {self.feet_ahead_m:+.2f} m ahead of the pelvis, lean {self.lean:+.2f}, "
                f"capture point {self.capture_outside_m * 100:.0f} cm outside the soles, "
                f"{'passes' if self.fall_check_excess == 0 else f'fails ({self.fall_check_excess:.2f})'} the env's fall checks")


@dataclass(frozen=True)
class LandingPosture:
    """Limits on the touch-down's posture, from the reference's at its own landing (`OpenLoopJumps.
    reference_posture`). A search that scores where the feet land can reach them forward from a flight that
    is no longer, and land sitting back: learn_cpu's far-jump prior (2.3 s segment) landed its ψ ≥ 0.88 m
    jumps upright or leaning back (lean −0.28 to +0.09) with the feet 0.21–0.49 m ahead of the pelvis, most
    of them pitching backward at 1–2 rad/s, where the reference lands leaning forward (+0.30) with its feet
    0.22 m ahead, pitching back at 0.59 rad/s (benchmarks/RESULTS.md, commit 0a98857)."""

    max_feet_ahead_m: float
    min_lean: float
    min_pitch_rate: float  # rad/s, + forward

    def excess(self, jump: Jump) -> float:
        return (max(0.0, jump.feet_ahead_m - self.max_feet_ahead_m) + max(0.0, self.min_lean - jump.lean)
                + 0.2 * max(0.0, self.min_pitch_rate - jump.pitch_rate))


class OpenLoopJumps:
    """Rolls out batches of offset curves over `steps` control steps of `motion` from frame `start`
    (MuJoCo C, 2 threads). Control step k aims at frame start + k + 1, as the env's step aims at the
    frame it ends on; past the motion's end, at its last frame. Each channel's curve is linear between
    `knots` evenly spaced knots over the window."""

    def __init__(self, motion, robot, start: int = 0, steps: int = 70, knots: int = KNOTS, physics: str | None = None):
        import mujoco

        from pipeline.envs.feedforward import zero_action_targets
        from pipeline.sim.model import build_sim_model, sensor_layout

        self.mujoco = mujoco
        self.model = build_sim_model(physics=physics)  # the env's physics preset (None: robot.yaml's default)
        self.layout = sensor_layout(self.model)
        self.substeps = int(round(robot.control_dt / self.model.opt.timestep))
        self.dt = self.model.opt.timestep
        self.segment = segment = motion.reorder_joints(robot.joint_names)  # qpos in the model's joint order
        self.start, self.steps = int(start), int(steps)
        last = segment.num_frames - 1
        if not 0 <= self.start < last or self.steps < 2:
            raise ValueError(f"open-loop window from frame {start} for {steps} steps does not fit {segment.num_frames} frames")
        targets = zero_action_targets(segment, "feedforward", robot, self.model)
        self.targets = targets[np.minimum(self.start + 1 + np.arange(self.steps), last)]
        self.num_joints = targets.shape[1]
        self.channel_joints = [[robot.joint_names.index(j) for j in pair] for pair in CHANNELS]
        if knots < 2:
            raise ValueError(f"open-loop curves need at least 2 knots, got {knots}")
        self.knots = int(knots)
        self.knot_steps = np.linspace(0, self.steps - 1, self.knots)
        # Motion bodies and the model's tracked sites are both in robot.tracked_body_names order.
        self.ankles = [segment.body_index("left_ankle"), segment.body_index("right_ankle")]

        data = mujoco.MjData(self.model)
        data.qpos[:], data.qvel[:] = segment.qpos()[self.start], segment.qvel()[self.start]
        mujoco.mj_forward(self.model, data)
        self.state_spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.initial_state = np.empty(mujoco.mj_stateSize(self.model, self.state_spec))
        mujoco.mj_getState(self.model, data, self.initial_state, self.state_spec)
        self.thread_data = [mujoco.MjData(self.model) for _ in range(2)]
        self._fall_check_tables()
        self.scratch = mujoco.MjData(self.model)

    def _fall_check_tables(self) -> None:
        """What the training env's fall checks (envs/config.py: TerminationConfig, relative to the reference)
        allow at each physics step: the lowest pelvis and the reference's tilt, at the frame being tracked."""
        from pipeline.envs.config import TerminationConfig

        checks = TerminationConfig()
        if not checks.relative_to_reference:
            raise RuntimeError("open_loop: the env's fall checks are not relative to the reference any more; update this")
        ref = self.segment.qpos()
        physics_steps = np.arange(1, self.steps * self.substeps + 1)
        frames = np.minimum(self.start + physics_steps // self.substeps, len(ref) - 1)
        self.min_pelvis_z = np.minimum(checks.min_base_height, ref[frames, 2] - checks.base_height_margin)
        self.ref_tilt_xy = quat.inverse_rotate(ref[frames, 3:7], DOWN)[:, :2]
        self.max_tilt_error = checks.max_tilt

    def fall_check_excess(self, qpos: np.ndarray, until: int) -> float:
        """Worst excess over the env's fall checks in physics steps [0, until): metres of pelvis below its
        lowest allowed height plus the tilt error past its limit (0: an env episode would not have ended)."""
        low = np.maximum(0.0, self.min_pelvis_z[:until] - qpos[:until, 2]).max()
        tilt = quat.inverse_rotate(qpos[:until, 3:7], DOWN)[:, :2]
        over = np.maximum(0.0, np.linalg.norm(tilt - self.ref_tilt_xy[:until], axis=-1) - self.max_tilt_error).max()
        return float(low + over)

    def curves(self, offsets: np.ndarray) -> np.ndarray:
        """(P, channels, knots) offsets (rad) -> (P, steps, joints) per-step joint offsets."""
        steps = np.arange(self.steps)
        out = np.zeros((len(offsets), self.steps, self.num_joints))
        for c, joints in enumerate(self.channel_joints):
            curve = np.stack([np.interp(steps, self.knot_steps, knots) for knots in offsets[:, c]])
            out[:, :, joints] = curve[:, :, None]
        return out

    def controls(self, curves: np.ndarray) -> np.ndarray:
        """(P, steps, joints) offsets -> (P, physics steps, nu) actuator targets."""
        return np.repeat(self.targets[None] + curves, self.substeps, axis=1)

    def jumps(self, offsets: np.ndarray) -> list[Jump | None]:
        """The jump of each (channels, knots) offset set; None where there was no flight to land."""
        return self.jumps_of_curves(self.curves(offsets))

    def jumps_of_curves(self, curves: np.ndarray) -> list[Jump | None]:
        from mujoco import rollout

        state, sensors = rollout.rollout(self.model, self.thread_data, self.initial_state[None],
                                         self.controls(curves), persistent_pool=True)
        # FULLPHYSICS state rows: time, qpos, qvel, ...
        nq, nv = self.model.nq, self.model.nv
        qpos, qvel = state[:, :, 1:1 + nq], state[:, :, 1 + nq:1 + nq + nv]
        contact = (sensors[:, :, slice(*self.layout.foot_contact)] > 0).any(axis=-1)
        sites = sensors[:, :, slice(*self.layout.site_pos)].reshape(len(curves), contact.shape[1], -1, 3)
        return [self._measure(contact[p], qpos[p], qvel[p], sites[p], state[p]) for p in range(len(curves))]

    def reference_posture(self, frame: int, feet_margin_m: float, lean_margin: float,
                          pitch_rate_margin: float) -> LandingPosture:
        """The limits a touch-down meets when its posture is within the margins of the reference's at `frame`."""
        qpos, qvel = self.segment.qpos()[frame], self.segment.qvel()[frame]
        feet_ahead = float(self.segment.body_pos[frame, self.ankles, 0].min() - qpos[0])
        lean = float(quat.inverse_rotate(qpos[3:7], DOWN)[0])
        return LandingPosture(feet_ahead + feet_margin_m, lean - lean_margin, float(qvel[4]) - pitch_rate_margin)

    def reference_capture_outside(self, frame: int) -> float:
        """`capture_outside` of the reference itself at `frame` of the motion (its touch-down)."""
        d = self.scratch
        d.qpos[:], d.qvel[:] = self.segment.qpos()[frame], self.segment.qvel()[frame]
        row = np.empty_like(self.initial_state)
        self.mujoco.mj_getState(self.model, d, row, self.state_spec)
        return self.capture_outside(row, self.segment.body_pos[frame, self.ankles, 0])

    def capture_outside(self, state_row: np.ndarray, ankle_x: np.ndarray) -> float:
        """How far (m) the whole-body capture point x + v/√(g/z) lies outside [rear heel, front toe]:
        a landing whose capture point is inside the soles can be stopped without a step."""
        mujoco, d = self.mujoco, self.scratch
        mujoco.mj_setState(self.model, d, state_row, self.state_spec)
        mujoco.mj_forward(self.model, d)
        mujoco.mj_subtreeVel(self.model, d)
        com, vel = d.subtree_com[0], d.subtree_linvel[0]
        capture = com[0] + vel[0] / np.sqrt(9.81 / com[2])
        return float(max(0.0, ankle_x.min() + SOLE_X[0] - capture, capture - ankle_x.max() - SOLE_X[1]))

    def _measure(self, contact, qpos, qvel, sites, state) -> Jump | None:
        # The first flight that lands (none: still in the air, or fallen on something other than the feet).
        for takeoff, b in find_flights(contact[:, None], 1.0 / self.dt, MIN_FLIGHT_S)[:1]:
            a = takeoff + 1  # the first frame in the air
            gravity = quat.inverse_rotate(qpos[b, 3:7], DOWN)
            ankles_x = sites[b, self.ankles, 0]
            rear_ankle_x = float(ankles_x.min())
            return Jump(feet_m=rear_ankle_x - float(sites[a - 1, self.ankles, 0].max()), landing_x=rear_ankle_x,
                        pelvis_m=float(np.linalg.norm(qpos[b, :2] - qpos[a - 1, :2])),
                        takeoff_s=float(a * self.dt), landing_s=float(b * self.dt),
                        tilt=float(np.linalg.norm(gravity[:2])),
                        pitch_rate=float(qvel[b, 4]), lowest_pelvis_m=float(qpos[a:b, 2].min()),
                        apex_pelvis_m=float(qpos[a:b, 2].max()),
                        capture_outside_m=self.capture_outside(state[b], ankles_x),
                        fall_check_excess=self.fall_check_excess(qpos, b + int(0.1 / self.dt)),
                        feet_ahead_m=rear_ankle_x - float(qpos[b, 0]), lean=float(gravity[0]))
        return None


def cross_entropy_search(jumps: OpenLoopJumps, land_by_s: float, capture_allowance_m: float, iterations: int,
                         population: int, rng: np.random.Generator, fall_checks: bool = False,
                         log=print, landable_only: bool = False, distance: str = "feet",
                         posture: LandingPosture | None = None) -> tuple[np.ndarray, Jump | None]:
    """Maximises distance − penalty over the offsets; returns the best offsets and their jump (None if
    no rollout flew at all). `distance`: "feet", the feet's travel in the air (`Jump.feet_m`: what the
    robot can jump), or "landing", where the rear foot lands (`Jump.landing_x`: what a gap anchored in
    the motion's frame asks). `fall_checks`: also penalise breaking the training env's fall checks.
    `landable_only`: return the furthest jump with no penalty at all (None if there was none). Without
    it a jump that breaks a limit by a hair can outscore every landable one, as a score it is; a caller
    that needs a jump it can use asks for this. `posture`: also penalise a touch-down outside these limits."""
    if distance not in ("feet", "landing"):
        raise ValueError(f"distance must be 'feet' or 'landing', got {distance!r}")
    reach = (lambda j: j.feet_m) if distance == "feet" else (lambda j: j.landing_x)
    shape = (len(CHANNELS), jumps.knots)
    mean, std = np.zeros(shape), np.full(shape, 0.4)
    elites = max(2, population // 10)
    best_score, best_offsets, best_jump = -np.inf, np.zeros(shape), None
    start = time.time()
    for it in range(iterations):
        offsets = mean + std * rng.standard_normal((population, *shape))
        offsets[0] = best_offsets  # keep the best so far in every batch
        found = jumps.jumps(offsets)
        scores = np.array([reach(j) - j.penalty(land_by_s, capture_allowance_m, fall_checks, posture) if j else -1.0
                           for j in found])
        order = np.argsort(-scores)
        for i in order:
            if scores[i] <= best_score:
                break
            if landable_only and not (found[i] and found[i].landable(land_by_s, capture_allowance_m, fall_checks, posture)):
                continue
            best_score, best_offsets, best_jump = scores[i], offsets[i].copy(), found[i]
            break
        elite = offsets[order[:elites]]
        mean = 0.3 * mean + 0.7 * elite.mean(axis=0)
        std = np.maximum(0.3 * std + 0.7 * elite.std(axis=0), 0.03)
        if log is not None and (it % 5 == 4 or it == iterations - 1):
            best = f"{reach(best_jump):.2f} m ({distance})" if best_jump is not None else "none landable yet"
            log(f"  iteration {it + 1:3d} ({time.time() - start:4.0f} s): best {best}, "
                f"elite mean {scores[order[:elites]].mean():.2f} m")
    return best_offsets, best_jump
