"""The `evaluate` and `report` stages' entry points (called by stages/evaluate.py, stages/report.py).

evaluate_variant writes into `out_dir` (results/<task>/<variant>/):
  metrics.json            DVC metrics: per range (easy, hard, overall) mean/std over runs, the
                          keyframe funnel (every episode pooled: how many reached each keyframe on track)
                          and the endings (every episode pooled: ran to the end, or fell which way, by which check)
  per_psi.csv, per_psi.json   DVC plots: metrics in ψ bins
  media/per_psi.png       success and errors vs ψ
  media/adapters.png      phase interval and adapter action magnitude over the episode, several ψ
  media/<range>_psi<ψ>.mp4    rollouts with the keyframe targets as markers
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

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
                     out_dir: str | Path, videos: bool = True, balance_export: str | Path | None = None) -> dict:
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
    if balance_export is not None:  # the chain from the stance at rest: rest_to_rest, nominal and randomised
        from pipeline.evaluation.chain_eval import merge_chain

        nominal, randomised = evaluate_rest_to_rest(task=task, variant=variant, data=data, env_cfg=env_cfg,
                                                    eval_cfg=eval_cfg, policy_dir=policy_dir,
                                                    balance_export=balance_export, psi_ranges=result.psi_ranges)
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
                render_rollout_video(policy, data, psi, make_env, media / f"{name}_psi{psi:.2f}.mp4", eval_cfg)
    return doc


def evaluate_rest_to_rest(*, task, variant, data, env_cfg, eval_cfg: EvalConfig, policy_dir, balance_export,
                          psi_ranges) -> tuple[dict, dict]:
    """The chain's evaluation (evaluation/chain_eval.py) of the policy exported with the balance policy into a
    scratch folder: (nominal, under the paper's domain randomisation)."""
    import tempfile

    from pipeline.envs.config import RandomizationConfig
    from pipeline.evaluation.chain_eval import evaluate_chain
    from pipeline.export.onnx_export import export_variant

    with tempfile.TemporaryDirectory(prefix="adamimic-chain-") as scratch:
        export = Path(scratch) / "export"
        export_variant(task=task, variant=variant, data=data, policy_dir=policy_dir, out_dir=export, env_cfg=env_cfg,
                       balance_export=balance_export)
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


def render_rollout_video(policy: PolicyRunner, data, psi: float, make_env, path: Path, eval_cfg: EvalConfig) -> Path:
    """One episode at ψ rendered from the env's world 0 onto the visual G1 with the task terrain."""
    import mujoco

    from pipeline.evaluation.video import MARKER_RGBA_PENDING, MARKER_RGBA_REACHED, Mp4Writer, SceneRenderer
    from pipeline.keyframes.terrain import apply_layout, terrain_builder, terrain_layout
    from pipeline.robot.g1 import build_model

    kinds = data.terrain.get("kind", "flat") if data.terrain else "flat"
    model = build_model(terrain=None if kinds == "flat" else terrain_builder(data.terrain), visual=True)
    if kinds != "flat":
        apply_layout(model, terrain_layout(data.terrain, psi))
    vis = mujoco.MjData(model)
    sample = int(np.argmin(np.abs(data.psi - psi)))
    frames = np.asarray(data.keyframe_frames)
    targets = data.motion.body_pos[frames] + data.keyframe_offsets[sample][:, None, :]  # (K, B, 3)
    kf_phase = frames / (data.motion.num_frames - 1)
    cfg = eval_cfg.video
    every = max(1, int(round(50 / cfg.fps)))
    renderer = SceneRenderer(model, cfg.width, cfg.height)
    writer = Mp4Writer(path, cfg.fps, cfg.width, cfg.height)
    state = {"step": 0}

    def on_frame(env, info):
        state["step"] += 1
        if state["step"] % every or state["step"] * 0.02 > cfg.max_seconds:
            return
        vis.qpos[:] = env.backend.qpos[0].detach().cpu().numpy().astype(np.float64)
        mujoco.mj_kinematics(model, vis)
        reached = kf_phase <= float(info["phase"][0]) + 1e-6
        colors = np.where(reached[:, None], MARKER_RGBA_REACHED, MARKER_RGBA_PENDING)
        colors = np.broadcast_to(colors[:, None], targets.shape[:2] + (4,))
        writer.add(renderer.render(vis, targets.reshape(-1, 3), colors.reshape(-1, 4), 0.03))

    try:
        trace_episode(policy, data, psi, make_env, frame_callback=on_frame)
    finally:
        renderer.close()
    if writer.count == 0:
        raise RuntimeError(f"no frame rendered for ψ={psi}")
    return writer.close()


def load_metrics(path: str | Path) -> dict:
    return json.loads(Path(path).read_text())
