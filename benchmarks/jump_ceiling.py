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
A search finds a lower bound of what the robot can do, not its maximum. The rollouts and the search are
`pipeline/priors/open_loop.py`; the pipeline's push prior (`pipeline/priors/push_prior.py`) is the third search
run on a task's D_edit.

    .venv/bin/python benchmarks/jump_ceiling.py [--motion far_jump] [--iterations 40] [--population 256] [--seed 0] [--knots 12]

`--knots`: how many knots each offset curve has over the 1.4 s (12, a knot every 0.13 s, is what the recorded
figures used; 20 reach further within the fall checks, RESULTS.md commit 2184b6a).

Ends with `ceiling_psi_m=<any timing> ceiling_psi_clip_timing_m=<by the reference's landing>
ceiling_psi_fall_checks_m=<also within the env's fall checks> psi_raw_m=<the clip's> zero_action_psi_m=<...>`:
the ψ of the furthest landable jumps found (nan if the best broke a landing limit).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from pipeline.priors.open_loop import CHANNELS, KNOTS, OpenLoopJumps, cross_entropy_search  # noqa: E402

CONTROL_STEPS = 70          # 1.4 s at 50 Hz: the push, the longest flights found, and the touch-down


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--motion", default="far_jump", help="a paper task whose edit moves the landing along x")
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--population", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--knots", type=int, default=KNOTS, help="knots per offset curve over the window")
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
    jumps = OpenLoopJumps(segment, robot, 0, CONTROL_STEPS, knots=args.knots)
    ankle_x = segment.body_pos[:, jumps.ankles, 0]
    clip_feet_m = float(ankle_x[landing].min() - ankle_x[takeoff].max())
    psi = lambda feet_m: task.psi.raw + feet_m - clip_feet_m  # noqa: E731
    allowance = jumps.reference_capture_outside(landing)
    print(f"{args.motion}: the G1 reference takes off at {takeoff / segment.fps:.2f} s and lands at "
          f"{clip_landing_s:.2f} s of the segment, its feet {clip_feet_m:.2f} m further: ψ_raw {task.psi.raw:.2f} m "
          f"(the task's ψ ranges: easy {task.psi.easy}, hard {task.psi.hard}); at its touch-down the capture point is "
          f"{allowance * 100:.0f} cm outside the soles, which the searched landings may be too")

    zero = jumps.jumps(np.zeros((1, len(CHANNELS), jumps.knots)))[0]
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
                                             fall_checks, log=lambda line: print(line, flush=True))
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
