"""Does stage 1 learn on 2 CPU cores? Goal: >= 90 % success within 20 minutes.

Imports ../shared/data/adamimic_smpl/far_jump.npz (or another shared clip: `--motion`, with its paper
task's edit, ψ ranges and terrain), retargets it to the G1, cuts about 1.5 s around the jump (from 0.5 s
before take-off to after landing), selects keyframes, builds D_edit and trains
stage 1 (variant adamimic_stage1, cpu profile) against the real TrackingEnv until the time budget.
Prints the training curve, where success is the trainer's (stochastic policy, randomised worlds,
half the episodes from a reference state): no termination and a mean body error <= 1 m at every
keyframe, and the ψ curriculum's running success by level at the end. Then evaluates the final
policy as the evaluate stage does (deterministic, from t = 0 over the whole segment, no
randomisation, 128 episodes), prints its success by ψ bin, and ends with that success: `success=<s>
minutes=<m>`. The same episodes are also scored on the paper's easy and hard ranges, and keyframe by
keyframe (the share that reached each one and the mean error there: where episodes are lost).

2-core machines differ (one stepped the env 2.4 times slower than another), so 20 minutes buy different
amounts of training there. `--iterations N` trains a fixed count instead, with no time limit and the
curricula following the count: figures that compare across machines.

With `--stage2-minutes M`, stage 2 (variant adamimic: phase and tracking adapters on the frozen stage-1
policy, episodes from t = 0) then trains for M more minutes and is evaluated on the same episodes; the
last line stays stage 1's, which is what the goal is about. `--stage1-from DIR` takes the stage-1 policy an
earlier run saved under its `--out` instead of training one (its line reads `minutes=0.0`), to train stage 2 on it;
give the same segment, ψ range, prior and `--set` overrides as that run.

With `--snapshots K`, stage 1 saves a checkpoint every `--snapshot-every N` iterations (default 10) and keeps
the last K; each is then evaluated on the same episodes, and so is the mean of their weights (observation
normalisers included) over the last 3, 5, ... K of them: how much a run's result depends on where it stops,
and whether averaging its tail steadies it (benchmarks/RESULTS.md, commit 136f1b8).

    .venv/bin/python benchmarks/learn_cpu.py [--motion far_jump] [--minutes 20 | --iterations N] [--segment 1.5] [--envs 192] [--out DIR]
        [--psi LOW HIGH] [--keyframe-spacing S] [--flat-ground] [--stage2-minutes M [--stage1-from DIR]] [--snapshots K [--snapshot-every N]]
        [--push-prior [--push-prior-knots K] [--push-prior-iterations N] [--push-prior-land-by-slack S] [--push-prior-reference-posture]
         | --no-push-prior | --push-prior-from DIR]
        [--set env.KEY=VALUE | train.KEY=VALUE ...]

On the far jump (any task whose edit lengthens the jump along +x) it first searches the task's push prior on
the segment (priors/push_prior.py: an open-loop push, scaled per ψ, added to the zero action; about a minute
on 2 cores, reported apart from the training's time, as the keyframe stage's are) and trains and evaluates
with it; `--no-push-prior` trains without (the default until commit b822369), `--push-prior-from DIR` reuses the
prior an earlier run saved.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from learn_report import evaluate_from_start, evaluate_snapshots, report  # noqa: E402  (beside this script)


def paper_task(motion_name: str):
    """The paper task named `motion_name` (pipeline/keyframes/paper_tasks.yaml), or exit naming the choices."""
    from pipeline.common.yaml_strict import load_yaml_strict
    from pipeline.keyframes.task_parsing import load_tasks

    tasks = load_tasks(load_yaml_strict(ROOT / "pipeline" / "keyframes" / "paper_tasks.yaml")["tasks"])
    if motion_name not in tasks:
        raise SystemExit(f"--motion {motion_name!r}: not a paper task (pipeline/keyframes/paper_tasks.yaml: "
                         f"{', '.join(tasks)})")
    return tasks[motion_name]


def jump_segment(task, segment_s: float | None):
    """The task's clip retargeted to the G1 at 50 fps, cut to `segment_s` from 0.5 s before its first
    take-off (or from the start when it has no flight); None: the whole clip. Returns (segment, (start,
    stop, frames))."""
    from pipeline.human.importers import load_human_motion
    from pipeline.keyframes.select import select_keyframes
    from pipeline.retarget import RetargetConfig, retarget

    human = load_human_motion(task.input_path(ROOT))
    motion, _ = retarget(human, RetargetConfig(), fps_out=50, progress=False)
    if segment_s is None:
        return motion, (0, motion.num_frames, motion.num_frames)
    full = select_keyframes(motion, task)
    if full.flights:
        takeoff, landing = full.flights[0]
        start = max(0, takeoff - int(0.5 * motion.fps))
    else:
        start = 0
    stop = min(motion.num_frames, start + int(round(segment_s * motion.fps)) + 1)
    return motion.slice(start, stop), (start, stop, motion.num_frames)


def build_data(segment_s: float, num_samples: int = 64, psi_range: tuple[float, float] | None = None,
               keyframe_spacing: float | None = None, motion_name: str = "far_jump", flat_ground: bool = False):
    from pipeline.keyframes.config import TerrainConfig

    task = paper_task(motion_name)
    if psi_range is not None:
        task = dataclasses.replace(task, psi=dataclasses.replace(task.psi, train=(tuple(psi_range),)))
    if keyframe_spacing is not None:
        spacing = dataclasses.replace(task.keyframes, spacing=keyframe_spacing, min_gap=min(task.keyframes.min_gap, keyframe_spacing / 2))
        task = dataclasses.replace(task, keyframes=spacing)
    if flat_ground:
        task = dataclasses.replace(task, terrain=TerrainConfig(kind="flat"))
    return segment_data(task, segment_s, num_samples)


def segment_data(task, segment_s: float | None, num_samples: int = 64):
    """D_edit on `jump_segment(task, segment_s)`: (tracking data, keyframes, span)."""
    from pipeline.keyframes.edit import build_tracking_data
    from pipeline.keyframes.select import select_keyframes

    segment, span = jump_segment(task, segment_s)
    keyframes = select_keyframes(segment, task)
    data = build_tracking_data(segment, task, keyframes, mode="edit", num_samples=num_samples, seed=0)
    return data, keyframes, span


def set_dotted(tree: dict, item: str) -> None:
    """`env.randomization.enabled=false` -> tree["env"]["randomization"]["enabled"] = False (YAML scalar)."""
    import yaml

    key, sep, value = item.partition("=")
    parts = key.split(".")
    if not sep or parts[0] not in tree or len(parts) < 2:
        raise SystemExit(f"--set {item!r}: expected env.KEY=VALUE or train.KEY=VALUE")
    node = tree[parts[0]]
    for part in parts[1:-1]:
        node = node.setdefault(part, {})
    node[parts[-1]] = yaml.safe_load(value)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=20.0)
    parser.add_argument("--iterations", type=int, default=0,
                        help="train this many iterations, with no time limit, instead of --minutes")
    parser.add_argument("--segment", type=float, default=1.5, help="seconds of the clip to track")
    parser.add_argument("--envs", type=int, default=None)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--motion", default="far_jump",
                        help="a paper task whose clip is at hand (the shared ones: far_jump, high_jump, jump_step_up, "
                             "jump_step_down, tennis_hit), with its edit, ψ ranges and terrain")
    parser.add_argument("--psi", type=float, nargs=2, metavar=("LOW", "HIGH"), default=None,
                        help="train on this ψ range instead of the paper task's train range")
    parser.add_argument("--keyframe-spacing", type=float, default=None,
                        help="seconds between uniform keyframes (default: the task's, 0.3)")
    parser.add_argument("--flat-ground", action="store_true",
                        help="train and evaluate on flat ground instead of the task's terrain (a probe: a short "
                             "landing then lands instead of falling into the far jump's gap)")
    parser.add_argument("--stage2-minutes", type=float, default=0.0,
                        help="then train stage 2 on the stage-1 policy for this long and evaluate it too")
    parser.add_argument("--stage1-from", type=Path, default=None, metavar="DIR",
                        help="skip stage 1: evaluate the policy an earlier run saved under DIR (its --out) and train "
                             "stage 2 on it")
    parser.add_argument("--snapshots", type=int, default=0, metavar="K",
                        help="keep stage 1's last K checkpoints and evaluate each, and their weight averages, too")
    parser.add_argument("--snapshot-every", type=int, default=10, metavar="N",
                        help="--snapshots: iterations between the kept checkpoints")
    parser.add_argument("--push-prior", action=argparse.BooleanOptionalAction, default=None,
                        help="search the task's push prior on this segment first (priors/push_prior.py, its time "
                             "reported apart from training's) and train and evaluate with it; saved under --out. "
                             "Default: on where the task's edit lengthens the jump along +x (the far jump)")
    parser.add_argument("--push-prior-from", type=Path, default=None, metavar="DIR",
                        help="train with the push prior an earlier --push-prior run saved: its run directory "
                             "or the push_prior directory it printed")
    parser.add_argument("--push-prior-knots", type=int, default=None, metavar="K",
                        help="--push-prior's search with K knots per push curve (default 20; PushPriorConfig's is 12)")
    parser.add_argument("--push-prior-iterations", type=int, default=None, metavar="N",
                        help="--push-prior's search for N cross-entropy iterations (default: PushPriorConfig's, 40)")
    parser.add_argument("--push-prior-land-by-slack", type=float, default=None, metavar="S",
                        help="--push-prior's search lets the touch-down come up to S s after the reference's landing "
                             "(default: PushPriorConfig's)")
    parser.add_argument("--push-prior-reference-posture", action="store_true",
                        help="--push-prior's search keeps the touch-down's posture near the reference's at its landing "
                             "(PushPriorConfig.reference_posture)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override env.* or train.* like params.yaml, e.g. env.randomization.enabled=false")
    args = parser.parse_args()
    if args.iterations < 0:
        parser.error("--iterations: must be >= 0 (0: train for --minutes)")
    if args.snapshots < 0 or args.snapshot_every < 1:
        parser.error("--snapshots: must be >= 0, and --snapshot-every >= 1")
    if args.stage1_from is not None:
        if args.snapshots:
            parser.error("--stage1-from: no stage-1 training, so no --snapshots")
        if not (args.stage1_from / "policy" / "config.json").exists():
            parser.error(f"--stage1-from {args.stage1_from}: no policy/config.json there (give an earlier run's --out)")
    if args.push_prior and args.push_prior_from:
        parser.error("--push-prior-from: a saved prior instead of a search, not with --push-prior")
    if args.push_prior is None:
        edit = paper_task(args.motion).edit
        args.push_prior = args.push_prior_from is None and edit.mode == "x" and edit.sign == 1.0
    for flag, value in (("--push-prior-knots", args.push_prior_knots), ("--push-prior-iterations", args.push_prior_iterations),
                        ("--push-prior-land-by-slack", args.push_prior_land_by_slack),
                        ("--push-prior-reference-posture", args.push_prior_reference_posture or None)):
        if value is not None and not args.push_prior:
            parser.error(f"{flag}: only with --push-prior (a saved prior keeps the search it came from)")

    import torch

    from pipeline.envs.config import EnvConfig
    from pipeline.rl.config import TrainConfig
    t0 = time.time()
    data, keyframes, (start, stop, total) = build_data(args.segment, psi_range=args.psi, keyframe_spacing=args.keyframe_spacing,
                                                       motion_name=args.motion, flat_ground=args.flat_ground)
    print(f"[learn_cpu] {args.motion} frames {start}..{stop} of {total}; keyframes {keyframes.frames.tolist()} "
          f"{list(keyframes.labels)}; prepared in {time.time() - t0:.0f} s", flush=True)

    # Sized by time (0 iterations train until the limit, and the curricula follow the clock) or by count.
    overrides = {"env": {}, "train": {"profile": "cpu", "variant": "adamimic_stage1", "iterations_stage1": args.iterations,
                                      "time_limit_stage1_s": 0.0 if args.iterations else args.minutes * 60.0,
                                      "save_interval": args.snapshot_every if args.snapshots else 50,
                                      "keep_checkpoints": max(2, args.snapshots)}}
    if args.envs:  # the worlds of either stage-1 trainer (train.algorithm)
        overrides["train"]["ppo"] = {"num_envs": args.envs}
        overrides["train"]["fast_td3"] = {"num_envs": args.envs}
    for item in args.set:
        set_dotted(overrides, item)
    cfg = TrainConfig.from_dict(overrides["train"])
    env_cfg = EnvConfig.from_dict(overrides["env"])

    out = args.out or Path(tempfile.mkdtemp(prefix="learn_cpu_"))
    if args.push_prior or args.push_prior_from:
        from pipeline.priors.push_prior import PushPriorConfig, build_push_prior, load_push_prior, write_push_prior
        from pipeline.robot.g1 import load_robot_config

        if args.push_prior_from:
            # Either the run's --out or the directory the run printed as "saved to": both name the same prior.
            prior_dir = args.push_prior_from
            if not (prior_dir / "push_prior.json").exists():
                prior_dir = prior_dir / "push_prior"
            data.push_prior = load_push_prior(prior_dir, data.motion.num_frames,
                                              load_robot_config().joint_names)
            if data.push_prior is None:
                raise SystemExit(f"--push-prior-from {args.push_prior_from}: its push_prior.json has no prior")
        else:
            t_prior = time.time()
            # 20 knots: every run over the goal trained on such a prior (benchmarks/RESULTS.md, commits ff6fc64-b822369).
            search = {"knots": 20 if args.push_prior_knots is None else args.push_prior_knots}
            if args.push_prior_iterations is not None:
                search["iterations"] = args.push_prior_iterations
            if args.push_prior_land_by_slack is not None:
                search["land_by_slack_s"] = args.push_prior_land_by_slack
            if args.push_prior_reference_posture:
                search["reference_posture"] = True
            prior_cfg = PushPriorConfig(enabled=True, **search)
            data.push_prior = build_push_prior(data, prior_cfg, log=lambda line: print(line, flush=True),
                                               physics=env_cfg.physics)  # searched on the env's physics
            write_push_prior(out / "push_prior", data.push_prior)
            print(f"[learn_cpu] push prior searched in {(time.time() - t_prior) / 60:.1f} minutes (not counted in "
                  f"training's), saved to {out / 'push_prior'}", flush=True)
        prior = data.push_prior
        print(f"[learn_cpu] push prior: ψ {prior.summary['psi_reached']:.2f} m at w = 1; w(ψ) anchors "
              + ", ".join(f"{p:.2f}:{w:.3f}" for p, w in zip(prior.psi_anchors, prior.weight_anchors)), flush=True)

    torch.set_num_threads(2)
    if args.stage1_from is not None:
        stage1_policy = args.stage1_from / "policy"
        ev, episodes = evaluate_from_start(stage1_policy, data, env_cfg)
        report(f"stage 1 from {stage1_policy}, evaluation from t = 0 (deterministic, no randomisation, "
               f"{ev['episodes']} episodes)", ev, episodes, data)
        minutes = 0.0
    else:
        stage1_policy = out / "policy"
        ev, minutes = train_and_report_stage1(args, data, env_cfg, cfg, out)
    if args.stage2_minutes > 0:
        from pipeline.rl.training import train_stage2

        stage2_cfg = TrainConfig.from_dict({**overrides["train"], "variant": "adamimic", "iterations_stage2": 0,
                                            "time_limit_stage2_s": args.stage2_minutes * 60.0})
        t2 = time.time()
        train_stage2(data, env_cfg, stage2_cfg, out / "stage2", stage1_dir=stage1_policy, tensorboard=False,
                     progress=False, log=print)
        ev2, episodes2 = evaluate_from_start(out / "stage2" / "policy", data, env_cfg)
        report(f"stage 2 after {(time.time() - t2) / 60:.1f} more minutes, same episodes", ev2, episodes2, data)
    print(f"success={ev['success'] / 100:.3f} minutes={minutes:.1f}")


def train_and_report_stage1(args, data, env_cfg, cfg, out: Path):
    """Stage 1 with its training curve printed, then its evaluation from t = 0. Returns (evaluation, minutes)."""
    import json

    from pipeline.rl.training import train_stage1

    t1 = time.time()
    metrics = train_stage1(data, env_cfg, cfg, out, tensorboard=False, progress=False, log=print)
    minutes = (time.time() - t1) / 60.0
    history = json.loads((out / "history.json").read_text())
    cols = [("iteration", "{:9d}", "iteration"), ("minutes", "{:7.2f}", None), ("env_steps", "{:9d}", "env_steps"),
            ("success", "{:7.3f}", "success_rate"), ("ep_len", "{:6.1f}", "episode_length"),
            ("fall_h", "{:6.2f}", "ended_by_base_height"), ("fall_t", "{:6.2f}", "ended_by_tilt"),
            ("kf_err", "{:6.2f}", "ended_by_keyframe_error"), ("ret_sparse", "{:10.1f}", "return_sparse"),
            ("ret_dense", "{:9.1f}", "return_dense"), ("std", "{:5.2f}", "action_std"),
            ("kf_thr", "{:6.2f}", "termination_threshold"), ("pen", "{:4.2f}", "penalty_scale"),
            ("psi_lvl", "{:7.2f}", "psi_level")]
    print("  ".join(name for name, _, _ in cols))
    stride = max(1, len(history) // 30)
    rows = history[::stride]
    if rows[-1] is not history[-1]:
        rows.append(history[-1])
    for h in rows:
        cells = []
        for name, fmt, key in cols:
            value = h["seconds"] / 60 if key is None else h.get(key, float("nan"))
            cells.append(fmt.format(value) if not (isinstance(value, float) and value != value) else "nan".rjust(len(name)))
        print("  ".join(c.rjust(len(n)) for c, (n, _, _) in zip(cells, cols)))
    if "psi_level_success" in history[-1]:
        rates, sides = history[-1]["psi_level_success"], history[-1].get("psi_level_side")
        if sides is None:
            text = " ".join(f"{v:.2f}" for v in rates)
        else:
            text = " | ".join(f"{name}: " + " ".join(f"{v:.2f}" for v, s in zip(rates, sides) if s == side)
                              for side, name in enumerate(("shorter", "farther")) if side in sides)
        print("[learn_cpu] ψ curriculum at the end, running success by level (bottom = nearest the clip's ψ): " + text)
    print(f"[learn_cpu] run dir {out} (training_curve.png, metrics.json)")
    train_success = metrics.get("success_rate") or 0.0
    ev, episodes = evaluate_from_start(out / "policy", data, env_cfg)
    print(f"[learn_cpu] training episodes (stochastic policy, randomised, half from a reference state): "
          f"success {train_success:.3f}")
    report(f"stage 1, evaluation from t = 0 (deterministic, no randomisation, {ev['episodes']} episodes)",
           ev, episodes, data)
    if args.snapshots:
        evaluate_snapshots(out, args.snapshots, data, env_cfg)
    return ev, minutes


if __name__ == "__main__":
    main()
