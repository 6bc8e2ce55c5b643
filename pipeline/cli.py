"""Command-line plumbing shared by the DVC stage scripts and the `adamimic` command.

A stage script is three lines: it hands its `run(params, args)` function to `stage_main`, which
parses `--task/--variant`, loads and validates `params.yaml`, and turns bad input into one line on
stderr and exit code 2 (nothing half-written: every stage writes its outputs atomically).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable

from pipeline.common.errors import PipelineInputError


def stage_parser(description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--params", default="params.yaml", help="parameters file (default: params.yaml)")
    parser.add_argument("--task", help="task name, a key of `tasks:` in params.yaml")
    parser.add_argument("--variant", help="training variant (see `variants:` in params.yaml)")
    parser.add_argument("--resume", action="store_true", help="continue training from the latest checkpoint")
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
    """`adamimic <command>`: user-facing tools beside `dvc repro` (play, share, sim2sim)."""
    parser = argparse.ArgumentParser(prog="adamimic", description=main.__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    play = sub.add_parser("play", help="roll out an exported policy at one psi into an mp4")
    play.add_argument("policy", type=Path, help="exported policy folder (policy.onnx + policy.json)")
    play.add_argument("--psi", type=float, required=True, help="task variable, metres")
    play.add_argument("--out", type=Path, default=Path("play.mp4"))
    play.add_argument("--seconds", type=float, default=None)

    sim2sim = sub.add_parser("sim2sim", help="deployment-style MuJoCo loop on the ONNX policy alone")
    sim2sim.add_argument("policy", type=Path)
    sim2sim.add_argument("--psi", type=float, nargs="+", required=True)

    share = sub.add_parser("share", help="write a dataset or policy folder in hub format; push if online")
    share.add_argument("path", type=Path, help="a dataset folder (meta/info.json) or policy folder (config.json)")
    share.add_argument("--out", type=Path, required=True, help="hub-format folder to write")
    share.add_argument("--repo-id", help="Hugging Face repo id to push to (needs network and a token)")

    args = parser.parse_args(argv)
    try:
        if args.command == "play":
            from pipeline.export.play import play_to_mp4

            play_to_mp4(args.policy, psi=args.psi, out=args.out, seconds=args.seconds)
            print(f"wrote {args.out}")
        elif args.command == "sim2sim":
            from pipeline.export.sim2sim import run_sim2sim

            print(run_sim2sim(args.policy, psi_values=args.psi))
        elif args.command == "share":
            from pipeline.share import share

            print(share(args.path, args.out, repo_id=args.repo_id))
    except PipelineInputError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
