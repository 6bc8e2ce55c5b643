"""Stage-1 trainers side by side: PPO against fast_td3 on the same task, segment and wall-clock minutes.

Builds the task's data once (learn_cpu's retarget, keyframes and D_edit), then for each trainer in
`--algorithms` trains stage 1 (variant adamimic_stage1, cpu profile, `train.algorithm` set) for
`--minutes` of wall time, one after the other on the same machine, and evaluates it as the evaluate
stage does (deterministic, from t = 0, no randomisation). Prints each run's training figures at the
same minutes and at the same env steps (success of the training episodes, their sparse return,
their length), then one line per trainer and the ratios of the last to the first:

    <algorithm> success=<s> train_success=<s> return_sparse=<r> env_steps=<n> minutes=<m>

Segments: `--segment S` cuts S seconds from 0.5 s before the clip's first take-off (learn_cpu's cut; on
the far jump 2.3 s reaches the stand after the landing); `--whole` tracks the whole clip from t = 0.

    .venv/bin/python benchmarks/compare_trainers.py [--motion far_jump] [--input PATH] [--segment 2.3 | --whole]
        [--minutes 20] [--algorithms ppo fast_td3] [--push-prior-from DIR] [--out DIR] [--set train.KEY=VALUE ...]

A 2-core machine shared with other work gives indicative figures only: the ratio holds for the minutes
it was measured in; run it on a quiet machine for figures to file.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import learn_cpu  # noqa: E402  (its data building, evaluation and --set parsing)


def row_at(history: list[dict], key: str, value: float) -> dict | None:
    """The last history row whose `key` is <= value."""
    rows = [h for h in history if h[key] <= value]
    return rows[-1] if rows else None


def cell(h: dict | None) -> str:
    if h is None:
        return "        -"
    return (f"{h.get('success_rate', float('nan')):5.3f} {h.get('return_sparse', float('nan')):7.1f} "
            f"{h.get('episode_length', float('nan')):5.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motion", default="far_jump")
    parser.add_argument("--input", type=Path, default=None, help="the clip (default: the paper task's input)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--segment", type=float, default=2.3, help="seconds from 0.5 s before the first take-off")
    where.add_argument("--whole", action="store_true", help="the whole clip from t = 0")
    parser.add_argument("--minutes", type=float, default=20.0, help="wall-clock training minutes per trainer")
    parser.add_argument("--algorithms", nargs="+", default=["ppo", "fast_td3"])
    parser.add_argument("--push-prior-from", type=Path, default=None, metavar="DIR",
                        help="a push prior an earlier learn_cpu run saved (default: none, for both trainers)")
    parser.add_argument("--episodes", type=int, default=128, help="evaluation episodes from t = 0")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    args = parser.parse_args()

    import torch

    from pipeline.envs.config import EnvConfig
    from pipeline.rl.config import TrainConfig
    from pipeline.rl.training import train_stage1

    task = learn_cpu.paper_task(args.motion)
    if args.input is not None:
        task = dataclasses.replace(task, input=str(args.input.resolve()))
    t0 = time.time()
    data, keyframes, (start, stop, total) = learn_cpu.segment_data(task, None if args.whole else args.segment)
    label = "whole clip from t = 0" if args.whole else f"{args.segment:g} s from 0.5 s before take-off"
    print(f"[compare] {args.motion}, {label}: frames {start}..{stop} of {total}; keyframes {keyframes.frames.tolist()}; "
          f"prepared in {time.time() - t0:.0f} s", flush=True)
    if args.push_prior_from is not None:
        from pipeline.priors.push_prior import load_push_prior
        from pipeline.robot.g1 import load_robot_config

        prior_dir = args.push_prior_from
        if not (prior_dir / "push_prior.json").exists():
            prior_dir = prior_dir / "push_prior"
        data.push_prior = load_push_prior(prior_dir, data.motion.num_frames, load_robot_config().joint_names)

    out = args.out or Path(tempfile.mkdtemp(prefix="compare_trainers_"))
    torch.set_num_threads(2)
    results = {}
    for algorithm in args.algorithms:
        overrides = {"env": {}, "train": {"profile": "cpu", "variant": "adamimic_stage1", "algorithm": algorithm,
                                          "iterations_stage1": 0, "time_limit_stage1_s": args.minutes * 60.0,
                                          "save_interval": 50}}
        for item in args.set:
            learn_cpu.set_dotted(overrides, item)
        cfg = TrainConfig.from_dict(overrides["train"])
        env_cfg = EnvConfig.from_dict(overrides["env"])
        run_dir = out / algorithm
        print(f"[compare] training {algorithm} for {args.minutes:g} minutes in {run_dir}", flush=True)
        t1 = time.time()
        train_stage1(data, env_cfg, cfg, run_dir, tensorboard=False, progress=False, log=print)
        minutes = (time.time() - t1) / 60.0
        history = json.loads((run_dir / "history.json").read_text())
        ev, episodes = learn_cpu.evaluate_from_start(run_dir / "policy", data, env_cfg, episodes=args.episodes)
        learn_cpu.report(f"{algorithm}, evaluation from t = 0 ({ev['episodes']} episodes)", ev, episodes, data)
        results[algorithm] = {"history": history, "success": ev["success"] / 100, "minutes": minutes}

    print("[compare] training episodes (success, sparse return, length) at the same wall-clock minutes:")
    print("  minutes  " + "  ".join(f"{a:>25}" for a in results))
    for k in range(1, 7):
        m = args.minutes * k / 6
        print(f"  {m:7.2f}  " + "  ".join(f"{cell(row_at(r['history'], 'seconds', m * 60)):>25}" for r in results.values()))
    common_steps = min(r["history"][-1]["env_steps"] for r in results.values())
    print("[compare] ... and at the same env steps:")
    print("  env_steps  " + "  ".join(f"{a:>25}" for a in results))
    for k in range(1, 7):
        s = common_steps * k / 6
        print(f"  {s:9.0f}  " + "  ".join(f"{cell(row_at(r['history'], 'env_steps', s)):>25}" for r in results.values()))
    for algorithm, r in results.items():
        last = r["history"][-1]
        print(f"{algorithm} success={r['success']:.3f} train_success={last.get('success_rate', float('nan')):.3f} "
              f"return_sparse={last.get('return_sparse', float('nan')):.1f} env_steps={last['env_steps']} "
              f"minutes={r['minutes']:.1f}")
    if len(results) >= 2:
        (a, ra), (b, rb) = list(results.items())[0], list(results.items())[-1]
        la, lb = ra["history"][-1], rb["history"][-1]
        print(f"ratio {b}/{a}: env_steps {lb['env_steps'] / la['env_steps']:.2f}, train_success "
              f"{lb.get('success_rate', 0.0):.3f}/{la.get('success_rate', 0.0):.3f}, eval success "
              f"{rb['success']:.3f}/{ra['success']:.3f}")


if __name__ == "__main__":
    main()
