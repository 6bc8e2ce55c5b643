"""The body of each DVC stage: read the previous stage's artifact, call the concern's code, write
this stage's artifact atomically. `stages/<name>.py` scripts only hand these to `cli.stage_main`."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
from pathlib import Path

from pipeline import paths
from pipeline.common.atomic import atomic_dir, write_text_atomic
from pipeline.common.errors import PipelineInputError
from pipeline.config import PipelineConfig


def run_import(params: PipelineConfig, args) -> None:
    """Import a human clip (SMPL npz, GVHMR .pt or video) into a human-motion dataset."""
    from pipeline.human.dataset import write_human
    from pipeline.human.importers import load_human_motion

    task = params.tasks[args.task]
    human = load_human_motion(task.input_path(params.path.parent))
    human.name = args.task
    write_human(paths.human_dir(args.task), human)
    print(f"{args.task}: {human.num_frames} frames at {human.fps:g} fps ({human.duration:.2f} s), "
          f"subject height {human.height:.2f} m")


def run_retarget(params: PipelineConfig, args) -> None:
    """Retarget the human motion to the G1 with IK; write the motion, a quality report, a preview."""
    from pipeline.human.dataset import read_human
    from pipeline.motion.dataset import write_motions
    from pipeline.retarget import write_preview
    from pipeline.retarget.core import retarget

    human = read_human(paths.human_dir(args.task))
    motion, report = retarget(human, params.retarget)
    motion.name = args.task
    out = paths.retarget_dir(args.task)
    write_motions(out / "motion", [motion])
    write_text_atomic(out / "quality.json", json.dumps(report, indent=1, default=float))
    write_preview(human, motion, out / "preview.mp4", duration_scale=report["duration_scale"], title=args.task)
    print(json.dumps(report, indent=1, default=float))


def run_keyframes(params: PipelineConfig, args) -> None:
    """Select keyframes and build D_edit, D_rule, the keyframe table, figure and D_rule video."""
    from pipeline.keyframes.outputs import build_task_outputs
    from pipeline.motion.dataset import read_motions

    task = params.tasks[args.task]
    (motion,) = read_motions(paths.retarget_dir(args.task) / "motion")
    with atomic_dir(paths.keyframes_dir(args.task)) as staging:
        written = build_task_outputs(motion, task, staging, seed=0)
    print("\n".join(f"{k}: {paths.keyframes_dir(args.task) / Path(v).name}" for k, v in written.items()))


def run_push_prior(params: PipelineConfig, args) -> None:
    """Search the push the env adds to the zero action per ψ (priors/push_prior.py), if the task asks for one."""
    from pipeline.keyframes.datasets import load_tracking_data
    from pipeline.priors.push_prior import build_push_prior, write_push_prior

    task = params.tasks[args.task]
    prior = None
    if task.push_prior.enabled:
        data = load_tracking_data(paths.keyframes_dir(args.task) / "d_edit")
        prior = build_push_prior(data, task.push_prior, log=lambda line: print(line, flush=True),
                                 physics=params.env.physics)
    with atomic_dir(paths.push_prior_dir(args.task)) as staging:
        write_push_prior(staging, prior)
    print(f"{args.task}: " + ("no push prior (tasks.<name>.push_prior.enabled is false)" if prior is None else
                              f"push prior to ψ {prior.summary['psi_reached']:.2f} m"))


def _train_config(params: PipelineConfig, variant: str):
    return dataclasses.replace(params.train, variant=variant)


def _tracking_data(params: PipelineConfig, task: str, variant: str, judged: bool = False):
    """The reference a variant tracks: D_edit, D_rule, or the unedited motion (zero offsets). `judged`: what it
    is evaluated on instead, D_edit's keyframes (ψ moves them, whatever the variant tracked) with the zero action
    it trained with."""
    from pipeline.keyframes.datasets import load_tracking_data

    from pipeline.priors.push_prior import load_push_prior
    from pipeline.robot.g1 import load_robot_config

    reference = _train_config(params, variant).variant_spec.reference
    base = paths.keyframes_dir(task)
    data = load_tracking_data(base / ("d_rule" if reference == "rule" and not judged else "d_edit"))
    if reference == "original":
        if not judged:
            data.keyframe_offsets = data.keyframe_offsets * 0.0
            data.dense_offsets = None
        return data  # the push prior jumps each sample's ψ: meaningless against the unedited motion
    data.push_prior = load_push_prior(paths.push_prior_dir(task), data.motion.num_frames,
                                      load_robot_config().joint_names)
    return data


def _evaluation_data(params: PipelineConfig, task: str, variant: str):
    """What a variant is judged on (`_tracking_data`'s `judged`)."""
    return _tracking_data(params, task, variant, judged=True)


def _chunk_s(args) -> float | None:
    """`--chunk-minutes` in seconds (None: train to the end in one go)."""
    minutes = getattr(args, "chunk_minutes", None)
    if minutes is None:
        return None
    if not minutes > 0:
        raise PipelineInputError("command line", "--chunk-minutes", f"must be > 0, got {minutes}")
    return 60.0 * minutes


def _finish_training(metrics: dict) -> None:
    """Print a training stage's metrics; a chunk that ended unfinished exits with EXIT_PAUSED."""
    from pipeline.cli import EXIT_PAUSED

    print(json.dumps(metrics, indent=1, default=float))
    if metrics.get("paused"):
        print("training paused at the end of its chunk: run the same command with --resume to go on",
              file=sys.stderr)
        sys.exit(EXIT_PAUSED)


def run_train_stage1(params: PipelineConfig, args) -> None:
    """Stage 1: sparse keyframe tracking (or the variant's dense baseline) with `train.algorithm`."""
    from pipeline.rl.training import train_stage1

    data = _tracking_data(params, args.task, args.variant)
    run_dir = paths.model_dir(args.task, args.variant) / "stage1"
    _finish_training(train_stage1(data, params.env, _train_config(params, args.variant), run_dir,
                                  resume=args.resume, chunk_s=_chunk_s(args), go_states=_go_states(params),
                                  handoff=_handoff(params, args.task, data)))


def _go_states(params: PipelineConfig) -> dict | None:
    """The states the chain's balance policy hands the robot over in at the go (env.go_starts), or None."""
    go = params.env.go_starts
    if go.prob <= 0:
        return None
    from pipeline.balance.go_states import record_go_states

    return record_go_states(balance_export(params), go.stands, stand_s=go.stand_s, seed=params.train.seed)


def _handoff(params: PipelineConfig, task: str, data):
    """Where the task's chain hands the robot back to the balance policy, for a task paid there
    (`env.rewards.weights.handoff_catch`), or None: the phase (clip.handoff_after_landing_s) and the balance
    policy's training checkpoint, whose critic judges the state (params.yaml `balance.out`/train/policy)."""
    if not params.env.rewards.weights.handoff_catch:
        return None
    from pipeline.envs.handoff_catch import Handoff
    from pipeline.export.chain import handoff_phase

    return Handoff(handoff_phase(data, params.tasks[task].clip.handoff_after_landing_s),
                   params.path.parent / params.balance.out / "train" / "policy")


def run_train_stage2(params: PipelineConfig, args) -> None:
    """Stage 2: phase and tracking adapters on the frozen stage-1 policy (if the variant has one)."""
    model_dir = paths.model_dir(args.task, args.variant)
    cfg = _train_config(params, args.variant)
    go_states = _go_states(params) if cfg.variant_spec.stage2 else None
    _finish_training(_train_stage2_into(params, args, cfg, model_dir, resume=args.resume, go_states=go_states))


def _train_stage2_into(params: PipelineConfig, args, cfg, model_dir: Path, resume: bool = False,
                       go_states: dict | None = None) -> dict:
    """Stage 2 on `model_dir`/stage1/policy into `model_dir`/final (`go_states`: `_go_states(params)`)."""
    from pipeline.rl.training import train_stage2

    final = model_dir / "final"
    if cfg.variant_spec.stage2:
        data = _tracking_data(params, args.task, args.variant)
        return train_stage2(data, params.env, cfg, final, stage1_dir=model_dir / "stage1" / "policy", resume=resume,
                            chunk_s=_chunk_s(args), go_states=go_states, handoff=_handoff(params, args.task, data))
    # One-stage variants: their final policy is the stage-1 policy, copied so later stages
    # read every variant from the same place.
    with atomic_dir(final) as staging:
        shutil.copytree(model_dir / "stage1" / "policy", staging / "policy")
        metrics = json.loads((model_dir / "stage1" / "metrics.json").read_text())
        (staging / "metrics.json").write_text(json.dumps(metrics, indent=1))
        (staging / "NOTE.md").write_text(f"Variant `{args.variant}` has no stage 2: this is its stage-1 policy.\n")
    return metrics


def _extra_seed(params: PipelineConfig, args) -> int:
    if args.seed is None or args.seed not in params.extra_seeds:
        raise PipelineInputError(params.path, "extra_seeds",
                                 f"--seed {args.seed} is not one of the extra seeds {list(params.extra_seeds)}")
    return args.seed


def run_train_seed(params: PipelineConfig, args) -> None:
    """Stage 1 and stage 2 again with another training seed (one of `extra_seeds`), everything else as
    the main run: the report's spread over seeds."""
    from pipeline.rl.training import train_stage1

    seed = _extra_seed(params, args)
    cfg = dataclasses.replace(_train_config(params, args.variant), seed=seed)
    model_dir = paths.seed_model_dir(args.task, args.variant, seed)
    stage1_dir = model_dir / "stage1"
    # stage 1 finished in an earlier chunk: resuming it would rewrite the policy stage 2 trains on
    stage1_done = (args.resume and (stage1_dir / "metrics.json").is_file()
                   and (stage1_dir / "policy" / "config.json").is_file())
    # recorded once for both stages, and not at all when neither trains
    go_states = _go_states(params) if not stage1_done or cfg.variant_spec.stage2 else None
    if stage1_done:
        stage1 = json.loads((stage1_dir / "metrics.json").read_text())
    else:
        data = _tracking_data(params, args.task, args.variant)
        stage1 = train_stage1(data, params.env, cfg, stage1_dir, resume=args.resume, chunk_s=_chunk_s(args),
                              go_states=go_states, handoff=_handoff(params, args.task, data))
        if stage1.get("paused"):
            _finish_training(stage1)
    final = _train_stage2_into(params, args, cfg, model_dir, resume=args.resume, go_states=go_states)
    _finish_training({"seed": seed, "stage1": stage1, "final": final, "paused": bool(final.get("paused"))})


def run_evaluate(params: PipelineConfig, args) -> None:
    """Evaluate a trained variant on the easy and hard psi ranges: metrics, per-psi plots, videos."""
    from pipeline.evaluation.run import evaluate_variant

    data = _evaluation_data(params, args.task, args.variant)
    model_dir, out_dir = paths.model_dir(args.task, args.variant), paths.results_dir(args.task, args.variant)
    if args.seed is not None:  # an extra seed's policy (evaluate_seed): its metrics, no videos
        seed = _extra_seed(params, args)
        model_dir = paths.seed_model_dir(args.task, args.variant, seed)
        out_dir = paths.seed_results_dir(args.task, args.variant, seed)
    doc = evaluate_variant(task=args.task, variant=args.variant, data=data, env_cfg=params.env,
                           eval_cfg=params.evaluate, policy_dir=model_dir / "final" / "policy",
                           out_dir=out_dir, videos=args.seed is None, balance_export=balance_export(params),
                           handoff_after_landing_s=params.tasks[args.task].clip.handoff_after_landing_s)
    print(json.dumps(doc, indent=1, default=float)[:4000])


def run_report(params: PipelineConfig, args) -> None:
    """The task's results table in the paper's layout (rows: variants) and the per-psi plot."""
    from pipeline.evaluation.report import write_report

    table = write_report(args.task, list(params.variants), results_dir=paths.results_dir(args.task),
                         out_dir=paths.report_dir(args.task), seeds=params.seeds,
                         seed_variants=list(params.seed_variants))
    print(Path(table).read_text())


def balance_export(params: PipelineConfig) -> Path:
    """The committed balance policy's export every task's chain stands with (params.yaml `balance.out`)."""
    return params.path.parent / params.balance.out / "export"


def run_export(params: PipelineConfig, args) -> None:
    """Export the deployed policy (stage 1 + adapters) to ONNX + metadata in hub format."""
    from pipeline.export.onnx_export import export_variant

    data = _evaluation_data(params, args.task, args.variant)
    model_dir = paths.model_dir(args.task, args.variant)
    result = export_variant(task=args.task, variant=args.variant, data=data, policy_dir=model_dir / "final" / "policy",
                            out_dir=model_dir / "export", env_cfg=params.env, balance_export=balance_export(params),
                            handoff_after_landing_s=params.tasks[args.task].clip.handoff_after_landing_s)
    print(f"exported {result.onnx} (torch/onnxruntime max abs diff {result.parity_max_abs_diff:.2e})")
