"""Command-line plumbing shared by the DVC stage scripts and the `adamimic` command.

A stage script is three lines: it hands its `run(params, args)` function to `stage_main`, which
parses `--task/--variant`, loads and validates `params.yaml`, and turns bad input into one line on
stderr and exit code 2 (nothing half-written: every stage writes its outputs atomically).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

from pipeline.common.errors import PipelineInputError


# A training stage that stopped at the end of its --chunk-minutes, unfinished (sysexits' EX_TEMPFAIL: run again)
EXIT_PAUSED = 75


def stage_parser(description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--params", default="params.yaml", help="parameters file (default: params.yaml)")
    parser.add_argument("--task", help="task name, a key of `tasks:` in params.yaml")
    parser.add_argument("--variant", help="training variant (see `variants:` in params.yaml)")
    parser.add_argument("--resume", action="store_true", help="continue training from the latest checkpoint")
    parser.add_argument("--chunk-minutes", type=float, default=None,
                        help="training: stop at the first checkpoint after this many minutes and exit with "
                             f"{EXIT_PAUSED}; rerun with --resume to go on (the wall-time caps count every chunk)")
    parser.add_argument("--seed", type=int, help="one of `extra_seeds` in params.yaml (train_seed, evaluate_seed)")
    return parser


def stage_main(run: Callable, description: str = "", argv: list[str] | None = None) -> None:
    from pipeline.config import load_params

    args = stage_parser(description or (run.__doc__ or "").strip().splitlines()[0]).parse_args(argv)
    try:
        params = load_params(args.params)
        if args.task is not None and args.task not in params.tasks:
            raise PipelineInputError(args.params, f"tasks.{args.task}", "no such task")
        run(params, args)
    except PipelineInputError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)


def main(argv: list[str] | None = None) -> None:
    """`adamimic <command>`: user-facing tools beside `dvc repro` (play, view, share, sim2sim, deploy, rehearse, sim-bridge)."""
    import math

    from pipeline.deploy.safety import SafetyConfig

    parser = argparse.ArgumentParser(prog="adamimic", description=main.__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    play = sub.add_parser("play", help="roll out an exported policy at one psi into an mp4")
    play.add_argument("policy", type=Path, help="exported policy folder (policy.onnx + policy.json)")
    play.add_argument("--psi", type=float, required=True, help="task variable, metres")
    play.add_argument("--out", type=Path, default=Path("play.mp4"))
    play.add_argument("--seconds", type=float, default=None, help="stop the video here (default: the whole chain)")

    sim2sim = sub.add_parser("sim2sim", help="deployment-style MuJoCo loop on the ONNX policies alone: stand, go, "
                                             "task, balance; one JSON line per psi")
    sim2sim.add_argument("policy", type=Path)
    sim2sim.add_argument("--psi", type=float, nargs="+", required=True)
    sim2sim.add_argument("--task-only", action="store_true",
                         help="the task policy alone, from the state it was trained to start in (no chain)")

    share = sub.add_parser("share", help="write a dataset or policy folder in hub format; push if online")
    share.add_argument("path", type=Path, help="a dataset folder (meta/info.json) or policy folder (config.json)")
    share.add_argument("--out", type=Path, required=True, help="hub-format folder to write")
    share.add_argument("--repo-id", help="Hugging Face repo id to push to (needs network and a token)")

    deploy = sub.add_parser("deploy", help="run the exported policy on a G1 over its low-level DDS interface")
    deploy.add_argument("policy", type=Path, help="exported policy folder (policy.onnx + policy.json)")
    deploy.add_argument("--psi", type=float, required=True, help="task variable, metres")
    deploy.add_argument("--interface", help="network interface that reaches the robot (lo for sim-bridge)")
    deploy.add_argument("--domain", type=int, default=0, help="DDS domain id (the robot uses 0)")
    deploy.add_argument("--go", action="store_true", help="start the policy as soon as the ramp ends (no key)")
    deploy.add_argument("--dry-run", action="store_true", help="run everything, publish no command")
    deploy.add_argument("--odometry-topic", help="nav_msgs Odometry_ topic (sim-bridge: rt/adamimic/odometry)")
    deploy.add_argument("--lockstep", action="store_true", help="against `sim-bridge --lockstep` only")
    defaults = SafetyConfig()
    for key, default, text in (("damping-s", defaults.damping_s, "damping at the start"),
                               ("ramp-s", defaults.ramp_s, "ramp to the default pose"),
                               ("stand-s", defaults.stand_s, "the balance policy holds the robot this long before "
                                                             "a go counts"),
                               ("hold-after-s", defaults.hold_after_s, "the balance policy after the episode, then "
                                                                       "exit; unset: until Ctrl-C"),
                               ("state-timeout-s", defaults.state_timeout_s, "LowState silence before damping"),
                               ("max-tilt-deg", round(math.degrees(defaults.max_tilt_rad), 1),
                                "base tilt before damping"),
                               ("joint-margin-rad", defaults.joint_margin_rad,
                                "joint beyond its limit by this before damping")):
        deploy.add_argument(f"--{key}", type=float, default=default, help=f"{text} (default {default})")

    view = sub.add_parser("view", help="serve an export (its chain, live), a retargeted task or a keyframes dataset "
                                       "in the browser (mjviser), on localhost")
    view.add_argument("path", type=Path, help="export folder, data/retargeted/<task> or data/keyframes/<task>/d_edit")
    view.add_argument("--port", type=int, default=8080)
    view.add_argument("--host", default="127.0.0.1", help="address to serve on (default: this machine only)")

    rehearse = sub.add_parser("rehearse", help="deploy against sim-bridge over loopback with the real timings; "
                                               "one JSON line per psi (success, standing, rest_to_rest)")
    rehearse.add_argument("policy", type=Path, help="exported policy folder with its balance policy (chain.json)")
    rehearse.add_argument("--psi", type=float, nargs="+", required=True)
    rehearse.add_argument("--keep-s", type=float, default=5.0, help="balance policy after the task (default 5)")

    bridge = sub.add_parser("sim-bridge", help="a MuJoCo G1 behind the robot's DDS interface, for `deploy`")
    bridge.add_argument("policy", type=Path, help="exported policy folder (for the scene, gains and start state)")
    bridge.add_argument("--psi", type=float, required=True)
    bridge.add_argument("--interface", default="lo")
    bridge.add_argument("--domain", type=int, default=0)
    bridge.add_argument("--lockstep", action="store_true", help="one control period per LowCmd (tests)")
    bridge.add_argument("--sim-dt", type=float, default=0.002, help="physics and motor-law period (default 500 Hz)")
    bridge.add_argument("--seconds", type=float, default=None, help="stop after this long (default: SIGTERM/Ctrl-C)")
    bridge.add_argument("--trace", type=Path, help="write the per-control-period pelvis and sites here (.npz)")
    bridge.add_argument("--gantry-s", type=float, default=4.0,
                        help="hang the robot on a virtual gantry, lower it onto its feet and let go this long after "
                             "the first command (deploy's damping + ramp); 0: start standing on the ground")

    args = parser.parse_args(argv)
    try:
        if args.command == "play":
            from pipeline.export.play import play_to_mp4

            play_to_mp4(args.policy, psi=args.psi, out=args.out, seconds=args.seconds)
            print(f"wrote {args.out}")
        elif args.command == "sim2sim" and args.task_only:
            from pipeline.export.sim2sim import run_sim2sim

            print(json.dumps(run_sim2sim(args.policy, psi_values=args.psi), indent=1))
        elif args.command == "sim2sim":
            from pipeline.export.chain import ChainRunner

            runner = ChainRunner(args.policy)
            for psi in args.psi:
                print(json.dumps(runner.run(psi).to_json()), flush=True)
        elif args.command == "share":
            from pipeline.share import share

            print(share(args.path, args.out, repo_id=args.repo_id))
        elif args.command == "deploy":
            from pipeline.deploy.controller import check_interface, run_deploy
            safety = SafetyConfig(damping_s=args.damping_s, ramp_s=args.ramp_s, stand_s=args.stand_s,
                                  hold_after_s=args.hold_after_s,
                                  state_timeout_s=args.state_timeout_s, max_tilt_rad=math.radians(args.max_tilt_deg),
                                  joint_margin_rad=args.joint_margin_rad)
            report = run_deploy(args.policy, args.psi, interface=check_interface(args.interface),
                                domain_id=args.domain, dry_run=args.dry_run, go_flag=args.go,
                                odometry_topic=args.odometry_topic, lockstep=args.lockstep, safety=safety)
            print(f"{report.end}: {report.message}")
            sys.exit(report.exit_code)
        elif args.command == "view":
            from pipeline.export.view import serve

            serve(args.path, host=args.host, port=args.port)
        elif args.command == "rehearse":
            from pipeline.deploy.rehearse import rehearse

            for line in rehearse(args.policy, args.psi, keep_s=args.keep_s):
                print(json.dumps(line), flush=True)
        elif args.command == "sim-bridge":
            from pipeline.deploy.bridge import SimBridge
            from pipeline.deploy.transport import DdsLink

            from pipeline.deploy.gantry import Gantry

            sim = SimBridge(args.policy, args.psi, link=DdsLink(args.domain, args.interface),
                            lockstep=args.lockstep, sim_dt=args.sim_dt,
                            gantry=Gantry(release_s=args.gantry_s, lower_s=min(2.0, args.gantry_s)) if args.gantry_s > 0 else None)
            print(f"sim-bridge: G1 on domain {args.domain} via {args.interface}", file=sys.stderr, flush=True)
            sim.run(args.seconds)
            if args.trace is not None:
                sim.save_trace(args.trace)
    except PipelineInputError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
