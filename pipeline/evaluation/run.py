"""The `evaluate` and `report` stages' entry points (called by stages/evaluate.py, stages/report.py).

evaluate_variant writes into `out_dir` (results/<task>/<variant>/):
  metrics.json            DVC metrics: per range (easy, hard, overall) mean/std over runs, the
                          keyframe funnel (every episode pooled: how many reached each keyframe on track)
                          and the endings (every episode pooled: ran to the end, or fell which way, by which check)
  per_psi.csv, per_psi.json   DVC plots: metrics in ψ bins
  media/per_psi.png       success and errors vs ψ
  media/adapters.png      phase interval and adapter action magnitude over the episode, several ψ
  media/<range>_psi<ψ>.mp4    rollouts of the exported chain (stand, go, task, stand), the reference as a ghost
"""

from __future__ import annotations

import json
import warnings
from contextlib import contextmanager
from pathlib import Path

from pipeline.common.atomic import atomic_dir
from pipeline.common.errors import PipelineInputError
from pipeline.evaluation.config import EvalConfig
from pipeline.evaluation.evaluate import (
    PolicyRunner,
    default_env_factory,
    evaluate_policy,
    spread_in_ranges,
    trace_episode,
)
from pipeline.evaluation.metrics import endings, keyframe_funnel, pooled_episodes
from pipeline.evaluation.report import metrics_document, per_psi_rows, plot_adapters, plot_per_psi, write_metrics, write_per_psi


def load_checked_policy(policy_dir: str | Path, task: str, expect: dict | None = None):
    """(module, meta) of a trained policy, refusing one from another task or robot."""
    from pipeline.rl.checkpoint import load_policy

    policy_dir = Path(policy_dir)
    if not policy_dir.is_dir():
        raise PipelineInputError(policy_dir, None, "trained policy folder not found (run the training stages)")
    module, meta = load_policy(policy_dir, expect=expect)
    if meta.get("task") not in (None, task):
        raise PipelineInputError(policy_dir / "config.json", "task",
                                 f"policy was trained for task {meta['task']!r}, not {task!r}")
    return module, meta


def _expectations(env_cfg, data) -> dict:
    from pipeline.envs.tracking_env import FRAME_OBS_DIM
    from pipeline.robot.g1 import load_robot_config

    robot = load_robot_config()
    return {"robot": robot.name, "joint_names": list(robot.joint_names),
            "actor_obs_dim": FRAME_OBS_DIM * env_cfg.observations.history,
            "action_offset": env_cfg.action_offset, "push_prior": getattr(data, "push_prior", None) is not None}


def evaluate_variant(*, task: str, variant: str, data, env_cfg, eval_cfg: EvalConfig, policy_dir: str | Path,
                     out_dir: str | Path, videos: bool = True, balance_export: str | Path | None = None,
                     handoff_after_landing_s: float | None = None) -> dict:
    module, meta = load_checked_policy(policy_dir, task, _expectations(env_cfg, data))
    policy = PolicyRunner(module, eval_cfg.device, eval_cfg.deterministic)
    make_env = default_env_factory(env_cfg, eval_cfg)
    result = evaluate_policy(policy, data, eval_cfg, make_env)
    doc = metrics_document(task, variant, result.runs, result.psi_ranges,
                           {"episodes_per_range": eval_cfg.episodes_per_range, "runs": eval_cfg.runs,
                            "psi_raw": float(data.psi_raw),
                            "domain_randomization": eval_cfg.domain_randomization, "policy_stage": meta.get("stage")})
    pooled = pooled_episodes(result.runs)
    doc["keyframe_funnel"] = funnel_rows(pooled, data, eval_cfg.success_threshold_m)
    doc["endings"] = endings(pooled)
    rows = per_psi_rows(result.runs, result.psi_ranges, eval_cfg.psi_grid_points)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with scratch_export(task=task, variant=variant, data=data, env_cfg=env_cfg, policy_dir=policy_dir,
                        balance_export=balance_export, handoff_after_landing_s=handoff_after_landing_s,
                        needed=videos or balance_export is not None) as export:
        if balance_export is not None:  # the chain from the stance at rest: rest_to_rest, nominal and randomised
            from pipeline.evaluation.chain_eval import merge_chain

            nominal, randomised = evaluate_rest_to_rest(export, eval_cfg, result.psi_ranges)
            merge_chain(doc, nominal)
            write_metrics(out_dir / "metrics_dr.json", chain_document(task, variant, randomised))
        write_metrics(out_dir / "metrics.json", doc)
        write_per_psi(out_dir / "per_psi.csv", rows, out_dir / "per_psi.json")
        with atomic_dir(out_dir / "media") as media:
            plot_per_psi({variant: rows}, result.psi_ranges, media / "per_psi.png")
            adapter_psi = [p for _, p in spread_in_ranges(result.psi_ranges, list(result.psi_ranges),
                                                          max(1, eval_cfg.adapter_psi_points // len(result.psi_ranges)))]
            traces = [trace_episode(policy, data, psi, make_env) for psi in adapter_psi]
            phase_rate = env_cfg_phase_rate(data)
            plot_adapters(traces, phase_rate, media / "adapters.png")
            if videos:
                for name, psi in _video_psi(eval_cfg, result.psi_ranges):
                    render_rollout_video(export, psi, media / f"{name}_psi{psi:.2f}.mp4", eval_cfg)
    return doc


@contextmanager
def scratch_export(*, task, variant, data, env_cfg, policy_dir, balance_export, handoff_after_landing_s=None,
                   needed: bool = True):
    """The policy exported (with its chain when a balance policy is given) into a temporary folder: what the
    chain evaluation and the videos run, the deployment loop a robot runs. None when not `needed`."""
    import tempfile

    if not needed:
        yield None
        return

    from pipeline.export.onnx_export import export_variant

    with tempfile.TemporaryDirectory(prefix="adamimic-eval-") as scratch:
        export = Path(scratch) / "export"
        export_variant(task=task, variant=variant, data=data, policy_dir=policy_dir, out_dir=export, env_cfg=env_cfg,
                       balance_export=balance_export, handoff_after_landing_s=handoff_after_landing_s)
        yield export


def evaluate_rest_to_rest(export: Path, eval_cfg: EvalConfig, psi_ranges: dict) -> tuple[dict, dict]:
    """The chain's evaluation (evaluation/chain_eval.py) of an export with its balance policy: (nominal, under
    the paper's domain randomisation)."""
    from pipeline.envs.config import RandomizationConfig
    from pipeline.evaluation.chain_eval import evaluate_chain

    per_range = eval_cfg.chain_episodes_per_range
    nominal = evaluate_chain(export, psi_ranges, per_range, seed=eval_cfg.seed)
    randomised = evaluate_chain(export, psi_ranges, per_range, randomization=RandomizationConfig(), seed=eval_cfg.seed)
    return nominal, randomised


def chain_document(task: str, variant: str, chain: dict) -> dict:
    """metrics_dr.json: the chain under domain randomisation, in metrics.json's layout (`ranges.<r>.<rate>.mean`)."""
    return {"task": task, "variant": variant, "domain_randomization": chain["domain_randomization"],
            "ranges": chain["ranges"], "chain": chain["chain"], "endings": chain["endings"],
            "episodes": [{k: e[k] for k in ("psi", "range", "success", "standing", "rest_to_rest", "end", "ended_in")}
                         for e in chain["episodes"]]}


def funnel_rows(episodes, data, threshold: float) -> list[dict]:
    """metrics.keyframe_funnel over `episodes` (EpisodeMetrics), with each keyframe's reference time and label."""
    rows = keyframe_funnel(episodes, data.num_keyframes, threshold)
    for row, frame, label in zip(rows, data.keyframe_frames, data.keyframe_labels):
        row["time_s"] = float(frame) / data.motion.fps
        row["label"] = label
    return rows


def env_cfg_phase_rate(data) -> float:
    from pipeline.robot.g1 import load_robot_config

    return load_robot_config().control_dt / data.motion.duration


def _video_psi(eval_cfg: EvalConfig, psi_ranges: dict) -> list[tuple[str, float]]:
    if eval_cfg.video.psi:
        out = []
        for psi in eval_cfg.video.psi:
            name = next((n for n, iv in psi_ranges.items() if any(lo <= psi <= hi for lo, hi in iv)), "outside")
            if name == "outside":
                warnings.warn(f"evaluate.video.psi: ψ = {psi:g} is outside the easy/hard ranges; rendering anyway")
            out.append((name, float(psi)))
        return out
    return spread_in_ranges(psi_ranges, list(psi_ranges), eval_cfg.video.per_range)


def render_rollout_video(export: Path, psi: float, path: Path, eval_cfg: EvalConfig) -> Path:
    """One rollout at ψ as a robot runs it, through `adamimic play`'s renderer: with a chain, standing on the
    balance policy, the go, the task and the stand after it; else the task from its trained start."""
    from pipeline.export.play import play_to_mp4

    cfg = eval_cfg.video
    return play_to_mp4(export, psi, path, seconds=cfg.max_seconds, width=cfg.width, height=cfg.height, fps=cfg.fps)


def load_metrics(path: str | Path) -> dict:
    return json.loads(Path(path).read_text())
