"""How far can the simulated G1 jump? An open-loop ceiling for the far jump's ψ, by search.

learn_cpu.py's policies jump 0.84–1.0 m where the clip jumps 1.1 m and the task asks up to 2 m. Is that
the robot or the training? This script asks the robot alone. It starts the G1 in the reference's state
0.5 s before the take-off, as learn_cpu's episodes do, on flat ground, and drives it open loop with
the zero action's joint targets (the reference + PD feedforward, `envs/feedforward.py`) plus offsets.
The offsets are piecewise linear in time, on five channels shared by both sides: hip pitch, knee,
ankle pitch, shoulder pitch and elbow. A cross-entropy search then picks the offsets that jump furthest.

The jump is how far the feet travel over the first flight of ≥ 0.1 s: the rear ankle at touch-down
minus the front ankle at take-off, which is what a gap has to be narrower than. The task edits ψ as
an offset from the clip's ψ_raw (the landing and all after it move by ψ − ψ_raw), so the script turns
each jump into the ψ it reaches: ψ_raw + (its feet travel − the G1 reference's). It also prints the
pelvis's travel over the flight (`retarget/core.py: jump_summary`, the sample's ψ_raw).

A jump only counts as landable if at touch-down the trunk's tilt is at most 0.6 (the norm of gravity's xy
in the pelvis frame; the far jump's G1 reference lands at 0.32, the sample's at 0.47), the pitch rate at
most 3 rad/s, the pelvis stayed above 0.5 m in the air, and the whole body's capture point (x + v/√(g/z)
of its centre of mass) lies no further outside the soles (rear heel to front toe) than the G1
reference's own does at its touch-down: a landing no harder to bring to rest than the clip's. A search
is penalised past these.
Nothing after the touch-down is simulated: standing up from the landing is the policy's job.

Three searches: one with any timing, and one that must touch down by the reference's own landing time
+ 0.04 s. Stage 1 tracks the edited landing keyframe at the reference's time, so the second one is
what a stage-1 policy can reach; stage 2's phase adapter may slow the reference down, as the first one does.
The third is the second within the training env's fall checks too (envs/config.py: TerminationConfig,
relative to the reference), from the start to 0.1 s after the touch-down: the pelvis no lower than
min(0.4 m, the reference's − 0.25 m) and the tilt within 0.8 of the reference's. A jump that breaks them
ends a training or evaluation episode before it lands, however well it would have landed.
A search finds a lower bound of what the robot can do, not its maximum.

    .venv/bin/python benchmarks/jump_ceiling.py [--motion far_jump] [--iterations 40] [--population 256] [--seed 0]

Ends with `ceiling_psi_m=<any timing> ceiling_psi_clip_timing_m=<by the reference's landing>
ceiling_psi_fall_checks_m=<also within the env's fall checks> psi_raw_m=<the clip's> zero_action_psi_m=<...>`:
the ψ of the furthest landable jumps found (nan if the best broke a landing limit).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from pipeline.common import quat  # noqa: E402

# The channels the search moves, each the same offset on both sides of the body.
CHANNELS = (("left_hip_pitch_joint", "right_hip_pitch_joint"), ("left_knee_joint", "right_knee_joint"),
            ("left_ankle_pitch_joint", "right_ankle_pitch_joint"),
            ("left_shoulder_pitch_joint", "right_shoulder_pitch_joint"), ("left_elbow_joint", "right_elbow_joint"))
KNOTS = 12
CONTROL_STEPS = 70          # 1.4 s at 50 Hz: the push, the longest flights found, and the touch-down
MIN_FLIGHT_S = 0.1
MAX_TILT, MAX_PITCH_RATE, MIN_FLIGHT_PELVIS_M = 0.6, 3.0, 0.5
DOWN = np.array([0.0, 0.0, -1.0])
SOLE_X = (-0.05, 0.13)      # heel and toe about the ankle (the G1's sole capsules, robots/g1/vendor/xmls)


@dataclass
class Jump:
    feet_m: float           # rear ankle at touch-down minus front ankle at take-off
    pelvis_m: float         # the pelvis's horizontal travel, take-off to touch-down
    takeoff_s: float
    landing_s: float
    tilt: float             # |gravity_xy| in the pelvis frame at touch-down
    pitch_rate: float       # rad/s at touch-down
    lowest_pelvis_m: float  # in the air
    apex_pelvis_m: float
    capture_outside_m: float  # how far the capture point lies outside the soles at touch-down (0: inside)
    fall_check_excess: float  # the training env's fall checks, worst excess until 0.1 s after touch-down (0: passed)

    def penalty(self, land_by_s: float, capture_allowance_m: float, fall_checks: bool = False) -> float:
        return (2.0 * max(0.0, self.tilt - MAX_TILT)
                + (5.0 * self.fall_check_excess if fall_checks else 0.0)
                + 0.2 * max(0.0, abs(self.pitch_rate) - MAX_PITCH_RATE)
                + 5.0 * max(0.0, MIN_FLIGHT_PELVIS_M - self.lowest_pelvis_m)
                + 5.0 * max(0.0, self.capture_outside_m - capture_allowance_m)
                + 10.0 * max(0.0, self.landing_s - land_by_s))

    def landable(self, land_by_s: float, capture_allowance_m: float, fall_checks: bool = False) -> bool:
        return self.penalty(land_by_s, capture_allowance_m, fall_checks) == 0.0

    def __str__(self) -> str:
        return (f"feet {self.feet_m:.2f} m (pelvis {self.pelvis_m:.2f} m), take-off {self.takeoff_s:.2f} s, "
                f"touch-down {self.landing_s:.2f} s, tilt {self.tilt:.2f}, pitch rate {self.pitch_rate:+.1f} rad/s, "
                f"pelvis {self.lowest_pelvis_m:.2f}-{self.apex_pelvis_m:.2f} m in the air, "
                f"capture point {self.capture_outside_m * 100:.0f} cm outside the soles, "
                f"{'passes' if self.fall_check_excess == 0 else f'fails ({self.fall_check_excess:.2f})'} the env's fall checks")


class OpenLoopJumps:
    """Rolls out batches of offset curves from the segment's first reference state (MuJoCo C, 2 threads)."""

    def __init__(self, segment, robot):
        import mujoco

        from pipeline.envs.feedforward import zero_action_targets
        from pipeline.sim.model import build_sim_model, sensor_layout

        self.mujoco = mujoco
        self.model = build_sim_model()
        self.layout = sensor_layout(self.model)
        self.substeps = robot.decimation
        self.dt = self.model.opt.timestep
        self.segment = segment = segment.reorder_joints(robot.joint_names)  # qpos in the model's joint order
        targets = zero_action_targets(segment, "feedforward", robot, self.model)
        # A control step aims at the frame it ends on (as the env does); past the segment, its last frame.
        pad = max(0, CONTROL_STEPS + 1 - len(targets))
        self.targets = np.concatenate([targets, np.repeat(targets[-1:], pad, axis=0)])[1:CONTROL_STEPS + 1]
        self.channel_joints = [[robot.joint_names.index(j) for j in pair] for pair in CHANNELS]
        self.knot_steps = np.linspace(0, CONTROL_STEPS - 1, KNOTS)
        # Motion bodies and the model's tracked sites are both in robot.tracked_body_names order.
        self.ankles = [segment.body_index("left_ankle"), segment.body_index("right_ankle")]

        data = mujoco.MjData(self.model)
        data.qpos[:], data.qvel[:] = segment.qpos()[0], segment.qvel()[0]
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
            raise SystemExit("jump_ceiling: the env's fall checks are not relative to the reference any more; update the script")
        ref = self.segment.qpos()
        frames = np.minimum(np.arange(1, CONTROL_STEPS * self.substeps + 1) // self.substeps, len(ref) - 1)
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

    def controls(self, offsets: np.ndarray) -> np.ndarray:
        """(P, channels, knots) offsets (rad) -> (P, physics steps, nu) actuator targets."""
        steps = np.arange(CONTROL_STEPS)
        ctrl = np.repeat(self.targets[None], len(offsets), axis=0)
        for c, joints in enumerate(self.channel_joints):
            curve = np.stack([np.interp(steps, self.knot_steps, knots) for knots in offsets[:, c]])
            ctrl[:, :, joints] += curve[:, :, None]
        return np.repeat(ctrl, self.substeps, axis=1)

    def jumps(self, offsets: np.ndarray) -> list[Jump | None]:
        from mujoco import rollout

        state, sensors = rollout.rollout(self.model, self.thread_data, self.initial_state[None],
                                         self.controls(offsets), persistent_pool=True)
        # FULLPHYSICS state rows: time, qpos, qvel, ...
        nq, nv = self.model.nq, self.model.nv
        qpos, qvel = state[:, :, 1:1 + nq], state[:, :, 1 + nq:1 + nq + nv]
        contact = (sensors[:, :, slice(*self.layout.foot_contact)] > 0).any(axis=-1)
        sites = sensors[:, :, slice(*self.layout.site_pos)].reshape(len(offsets), contact.shape[1], -1, 3)
        return [self._measure(contact[p], qpos[p], qvel[p], sites[p], state[p]) for p in range(len(offsets))]

    def reference_capture_outside(self, frame: int) -> float:
        """`capture_outside` of the reference itself at `frame` (its touch-down)."""
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
        lift_offs = np.flatnonzero(contact[:-1] & ~contact[1:]) + 1
        for a in lift_offs:
            touch = np.flatnonzero(contact[a:])
            if len(touch) == 0:
                return None  # still in the air, or fallen on something other than the feet
            b = a + touch[0]
            if (b - a) * self.dt < MIN_FLIGHT_S:
                continue
            gravity_xy = np.linalg.norm(quat.inverse_rotate(qpos[b, 3:7], DOWN)[:2])
            return Jump(feet_m=float(sites[b, self.ankles, 0].min() - sites[a - 1, self.ankles, 0].max()),
                        pelvis_m=float(np.linalg.norm(qpos[b, :2] - qpos[a - 1, :2])),
                        takeoff_s=float(a * self.dt), landing_s=float(b * self.dt), tilt=float(gravity_xy),
                        pitch_rate=float(qvel[b, 4]), lowest_pelvis_m=float(qpos[a:b, 2].min()),
                        apex_pelvis_m=float(qpos[a:b, 2].max()),
                        capture_outside_m=self.capture_outside(state[b], sites[b, self.ankles, 0]),
                        fall_check_excess=self.fall_check_excess(qpos, b + int(0.1 / self.dt)))
        return None


def cross_entropy_search(jumps: OpenLoopJumps, land_by_s: float, capture_allowance_m: float, iterations: int,
                         population: int, rng: np.random.Generator, fall_checks: bool = False) -> tuple[np.ndarray, Jump]:
    """Maximises the feet's travel − penalty over the offsets; returns the best offsets and their jump.
    `fall_checks`: also penalise breaking the training env's fall checks."""
    shape = (len(CHANNELS), KNOTS)
    mean, std = np.zeros(shape), np.full(shape, 0.4)
    elites = max(2, population // 10)
    best_score, best_offsets, best_jump = -np.inf, np.zeros(shape), None
    start = time.time()
    for it in range(iterations):
        offsets = mean + std * rng.standard_normal((population, *shape))
        offsets[0] = best_offsets  # keep the best so far in every batch
        found = jumps.jumps(offsets)
        scores = np.array([j.feet_m - j.penalty(land_by_s, capture_allowance_m, fall_checks) if j else -1.0 for j in found])
        order = np.argsort(-scores)
        if scores[order[0]] > best_score:
            best_score, best_offsets, best_jump = scores[order[0]], offsets[order[0]].copy(), found[order[0]]
        elite = offsets[order[:elites]]
        mean = 0.3 * mean + 0.7 * elite.mean(axis=0)
        std = np.maximum(0.3 * std + 0.7 * elite.std(axis=0), 0.03)
        if it % 5 == 4 or it == iterations - 1:
            print(f"  iteration {it + 1:3d} ({time.time() - start:4.0f} s): best {best_score:.2f} m of feet travel, "
                  f"elite mean {scores[order[:elites]].mean():.2f} m", flush=True)
    return best_offsets, best_jump


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--motion", default="far_jump", help="a paper task whose edit moves the landing along x")
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--population", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from learn_cpu import jump_segment, paper_task

    from pipeline.keyframes.select import select_keyframes
    from pipeline.robot.g1 import load_robot_config

    task = paper_task(args.motion)
    if task.edit.mode != "x":
        raise SystemExit(f"--motion {args.motion}: its ψ is not a jump distance (edit mode {task.edit.mode!r})")
    segment, _ = jump_segment(task, CONTROL_STEPS / 50.0)
    flights = select_keyframes(segment, task).flights
    if not flights:
        raise SystemExit(f"--motion {args.motion}: no flight in the clip")
    takeoff, landing = flights[0]
    clip_landing_s = landing / segment.fps
    robot = load_robot_config()
    jumps = OpenLoopJumps(segment, robot)
    ankle_x = segment.body_pos[:, jumps.ankles, 0]
    clip_feet_m = float(ankle_x[landing].min() - ankle_x[takeoff].max())
    psi = lambda feet_m: task.psi.raw + feet_m - clip_feet_m  # noqa: E731
    allowance = jumps.reference_capture_outside(landing)
    print(f"{args.motion}: the G1 reference takes off at {takeoff / segment.fps:.2f} s and lands at "
          f"{clip_landing_s:.2f} s of the segment, its feet {clip_feet_m:.2f} m further: ψ_raw {task.psi.raw:.2f} m "
          f"(the task's ψ ranges: easy {task.psi.easy}, hard {task.psi.hard}); at its touch-down the capture point is "
          f"{allowance * 100:.0f} cm outside the soles, which the searched landings may be too")

    zero = jumps.jumps(np.zeros((1, len(CHANNELS), KNOTS)))[0]
    zero_psi = psi(zero.feet_m) if zero else float("nan")
    print(f"zero action (the reference + feedforward, open loop): ψ {zero_psi:.2f} m, {zero if zero else 'no flight'}")
    rng = np.random.default_rng(args.seed)
    reached = {}
    clip_timed = f"touch-down by {clip_landing_s + 0.04:.2f} s"
    searches = (("any timing", np.inf, False), (clip_timed, clip_landing_s + 0.04, False),
                (f"{clip_timed}, within the training env's fall checks", clip_landing_s + 0.04, True))
    for name, land_by_s, fall_checks in searches:
        print(f"search, {name}: {args.iterations} iterations of {args.population} rollouts")
        offsets, jump = cross_entropy_search(jumps, land_by_s, allowance, args.iterations, args.population, rng,
                                             fall_checks)
        ok = jump.landable(land_by_s, allowance, fall_checks)
        landable = "landable" if ok else "NOT within the landing limits"
        print(f"  best: ψ {psi(jump.feet_m):.2f} m, {jump} ({landable})")
        # What a policy would have to output for it: the offsets in its action units (rad / action scale).
        units = [np.abs(offsets[c]).max() / robot.action_scale[jumps.channel_joints[c][0]] for c in range(len(CHANNELS))]
        print("  largest offset, in policy action units: " + ", ".join(
            f"{pair[0].removeprefix('left_').removesuffix('_joint')} {u:.1f}" for pair, u in zip(CHANNELS, units)))
        reached[name] = psi(jump.feet_m) if ok else float("nan")
    free, timed, checked = reached.values()
    print(f"ceiling_psi_m={free:.2f} ceiling_psi_clip_timing_m={timed:.2f} ceiling_psi_fall_checks_m={checked:.2f} "
          f"psi_raw_m={task.psi.raw:.2f} zero_action_psi_m={zero_psi:.2f}")


if __name__ == "__main__":
    main()
