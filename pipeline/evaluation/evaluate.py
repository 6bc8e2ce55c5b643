"""Evaluation runs: a policy in the TrackingEnv with ψ from the easy and hard ranges separately.

Deterministic actions, no domain randomisation (unless `EvalConfig.domain_randomization`), no
observation noise, episodes from t = 0, and no keyframe-error termination (the success metric
decides, not the training curriculum). Each world records its episodes until it has finished its
share, so short (failed) episodes are not over-represented. Records go through the pure metrics
in `metrics.py`; outputs are a metrics json, per-ψ csv/json (DVC plots), pngs and mp4s.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import start_episodes_at_zero
from pipeline.evaluation.config import EvalConfig
from pipeline.evaluation.metrics import EpisodeMetrics, EpisodeRecord, PsiReach, episode_metrics
from pipeline.keyframes.tracking_data import TrackingData


# ------------------------------------------------------------------------------ data and config
def range_mask(psi: np.ndarray, intervals) -> np.ndarray:
    psi = np.asarray(psi, dtype=np.float64)
    mask = np.zeros(psi.shape, dtype=bool)
    for lo, hi in intervals:
        mask |= (psi >= lo - 1e-9) & (psi <= hi + 1e-9)
    return mask


def subset_tracking_data(data: TrackingData, mask: np.ndarray) -> TrackingData:
    """The same task restricted to the ψ samples in `mask` (the evaluation env sweeps through them)."""
    mask = np.asarray(mask, dtype=bool)
    return replace(
        data,
        psi=data.psi[mask],
        keyframe_offsets=data.keyframe_offsets[mask],
        dense_offsets=None if data.dense_offsets is None else data.dense_offsets[mask],
    )


def nearest_sample_data(data: TrackingData, psi: float) -> TrackingData:
    mask = np.zeros(data.num_samples, dtype=bool)
    mask[int(np.argmin(np.abs(data.psi - psi)))] = True
    return subset_tracking_data(data, mask)


def evaluation_env_config(env_cfg, eval_cfg: EvalConfig):
    """The training env config made deterministic for evaluation (a deep copy)."""
    cfg = copy.deepcopy(env_cfg)
    start_episodes_at_zero(cfg)  # so every keyframe is scored
    if hasattr(cfg, "go_starts"):
        cfg.go_starts.prob = 0.0  # the batch scores from the stance itself; the chains start at the go
    if hasattr(cfg, "rewards"):
        cfg.rewards.weights.handoff_catch = 0.0  # the batch scores every keyframe to the phase's end; the chains hand over
    if hasattr(cfg, "sampling"):
        cfg.sampling.mode = "sweep"  # every ψ sample of a range in turn: equal weight, the same ψ for every policy
    if hasattr(cfg, "randomization"):
        cfg.randomization.enabled = bool(eval_cfg.domain_randomization)
    if hasattr(cfg, "observations") and not eval_cfg.domain_randomization:
        cfg.observations.odometry_noise_std = 0.0
    return cfg


# ------------------------------------------------------------------------------ the policy
class PolicyRunner:
    """(action, Δφ^Δ, adapter action magnitude) from a torch policy module.

    The module returns the joint action or (action, Δφ^Δ). When it has a stage-1 `base`, the
    adapter's contribution is the applied action minus the base action (its L2 norm is recorded
    for the adapters' figure). `deterministic=False` samples from the policy's Gaussian instead of
    taking its mean (a training policy's `sample` + `to_env`), as a robustness check."""

    def __init__(self, module: torch.nn.Module, device: str = "cpu", deterministic: bool = True):
        self.module = module.eval().to(device)
        self.device = device
        self.base = getattr(module, "base", None)
        self.deterministic = deterministic
        if not deterministic and not (hasattr(module, "sample") and hasattr(module, "to_env")):
            raise PipelineInputError("evaluate", "deterministic", "false needs a policy with sample() and to_env()")

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor):
        obs = obs.to(self.device)
        if self.deterministic:
            out = self.module(obs)
        else:
            out = self.module.to_env(obs, self.module.sample(obs)[0])
        action, dphi = (out[0], out[1]) if isinstance(out, (tuple, list)) else (out, None)
        if dphi is not None:
            dphi = dphi.reshape(-1)
        adapter = None
        if self.base is not None:
            base_out = self.base(obs)
            base_action = base_out[0] if isinstance(base_out, (tuple, list)) else base_out
            adapter = torch.linalg.vector_norm(action - base_action, dim=-1)
        return action, dphi, adapter


# ------------------------------------------------------------------------------ rollouts
def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def rollout(env, policy: Callable, episodes_per_env: int, num_keyframes: int,
            max_steps: int | None = None, on_step: Callable | None = None) -> list[EpisodeRecord]:
    """Runs until every world has finished `episodes_per_env` episodes; returns their records.

    Reads from `info` (env contract): keyframe_crossed, body_pos_error_w, body_pos_error_local,
    joint_acc, phase, psi; and info["keyframe_body_error_w"] when the env provides the error
    against the exact keyframe target (else body_pos_error_w on the crossing step),
    info["keyframe_miss_w"] (mean body position minus the keyframe target) when it has it, and
    info["terminated_by"] / info["tilt_error_xy"] for how each episode ended when it has them.
    """
    n = env.num_envs
    obs = env.reset()
    buffers: list[dict[str, list]] = [_empty_buffer() for _ in range(n)]
    finished = np.zeros(n, dtype=int)
    records: list[tuple[int, int, EpisodeRecord]] = []  # (episode index of its world, world, record)
    limit = max_steps if max_steps is not None else 10**7
    for _ in range(limit):
        action, dphi, adapter = policy(obs["actor"])
        obs, _, terminated, truncated, info = env.step(action, dphi)
        crossed = _np(info["keyframe_crossed"]).astype(bool)
        world = _np(info.get("keyframe_body_error_w", info["body_pos_error_w"]))
        if "keyframe_body_error_w" in info:
            world = np.where(crossed[:, None], world, _np(info["body_pos_error_w"]))
        miss = _np(info["keyframe_miss_w"]) if "keyframe_miss_w" in info else np.full((n, 3), np.nan)
        local = _np(info["body_pos_error_local"])
        acc = _np(info["joint_acc"])
        phase = _np(info["phase"])
        psi = _np(info["psi"])
        dphi_np = _np(dphi) if dphi is not None else np.zeros(n)
        adapter_np = _np(adapter) if adapter is not None else np.full(n, np.nan)
        ended = _np(terminated).astype(bool)
        done = ended | _np(truncated).astype(bool)
        if done.any():  # how the finished episodes ended (read only on the steps some end)
            fired = {name: _np(mask).astype(bool) for name, mask in (info.get("terminated_by") or {}).items()}
            tilt = _np(info["tilt_error_xy"]) if "tilt_error_xy" in info else None
        if on_step is not None:
            on_step(env, info, done)  # for done worlds the env already holds the next episode
        for i in np.flatnonzero(finished < episodes_per_env):
            b = buffers[i]
            b["world"].append(world[i]); b["local"].append(local[i]); b["crossed"].append(crossed[i])
            b["acc"].append(acc[i]); b["phase"].append(phase[i]); b["dphi"].append(dphi_np[i])
            b["adapter"].append(adapter_np[i]); b["psi"] = float(psi[i]); b["miss"].append(miss[i])
            if done[i]:
                b["ended_by"] = _checks_fired(fired, i, ended[i])
                b["end_tilt_error"] = tilt[i] if tilt is not None else None
                records.append((int(finished[i]), int(i), _to_record(b, num_keyframes)))
                buffers[i] = _empty_buffer()
                finished[i] += 1
        if np.all(finished >= episodes_per_env):
            break
    else:
        # out of steps: the unfinished episodes count as they are (they missed their keyframes)
        for i in np.flatnonzero(finished < episodes_per_env):
            if buffers[i]["world"]:
                records.append((int(finished[i]), int(i), _to_record(buffers[i], num_keyframes)))
    # In episode-then-world order, not finishing order: a caller that keeps the first N keeps the same
    # episodes whichever end first (finishing order would favour the short ones, i.e. the falls).
    return [record for _, _, record in sorted(records, key=lambda r: r[:2])]


def _checks_fired(fired: dict[str, np.ndarray], world: int, terminated: bool) -> tuple[str, ...] | None:
    """The env checks that ended `world`'s episode this step: () when it was not terminated (it ran to its
    end), None when it was but the env does not say why (no info["terminated_by"], or none of its checks fired)."""
    names = tuple(name for name, mask in fired.items() if mask[world])
    return names if names or not terminated else None


def _empty_buffer() -> dict[str, list]:
    return {"world": [], "local": [], "crossed": [], "acc": [], "phase": [], "dphi": [], "adapter": [], "miss": [],
            "psi": 0.0, "ended_by": None, "end_tilt_error": None}


def _to_record(b: dict, num_keyframes: int) -> EpisodeRecord:
    return EpisodeRecord(
        body_error_world=np.stack(b["world"]), body_error_local=np.stack(b["local"]),
        keyframe_crossed=np.array(b["crossed"]), joint_acc=np.stack(b["acc"]), psi=b["psi"],
        num_keyframes=num_keyframes, phase=np.array(b["phase"]), phase_rate_offset=np.array(b["dphi"]),
        adapter_action_norm=np.array(b["adapter"]), keyframe_miss=np.stack(b["miss"]),
        ended_by=b["ended_by"], end_tilt_error=b["end_tilt_error"],
    )


@dataclass
class EvaluationResult:
    runs: list[dict[str, list[EpisodeMetrics]]]  # per run: range name -> episodes
    psi_ranges: dict[str, list]


def default_env_factory(env_cfg, eval_cfg: EvalConfig):
    def make(data: TrackingData, num_envs: int, seed: int):
        from pipeline.envs.tracking_env import TrackingEnv

        env = TrackingEnv(evaluation_env_config(env_cfg, eval_cfg), data, num_envs=num_envs,
                          backend=eval_cfg.backend, device=eval_cfg.device, seed=seed)
        env.termination_threshold = math.inf  # score keyframes with the paper's metric instead
        return env
    return make


def evaluate_policy(policy: PolicyRunner, data: TrackingData, eval_cfg: EvalConfig,
                    make_env: Callable) -> EvaluationResult:
    """`runs` × ranges of `episodes_per_range` episodes; env per (run, range) seeded differently."""
    ranges = {}
    for name in eval_cfg.ranges:
        intervals = data.psi_ranges.get(name)
        if not intervals:
            raise PipelineInputError(f"task {data.task}", f"psi.{name}", "range not declared for this task")
        mask = range_mask(data.psi, intervals)
        if not mask.any():
            raise PipelineInputError(f"task {data.task}", f"psi.{name}",
                                     f"no ψ sample of the tracking data lies in {intervals}")
        ranges[name] = (intervals, subset_tracking_data(data, mask))
    reach = PsiReach.fit(data.psi, data.keyframe_offsets)  # on every sample: one axis for all ranges
    runs = []
    for run in range(eval_cfg.runs):
        per_range = {}
        for r, (name, (_, subset)) in enumerate(ranges.items()):
            num_envs = min(eval_cfg.num_envs, eval_cfg.episodes_per_range)
            per_env = math.ceil(eval_cfg.episodes_per_range / num_envs)
            seed = eval_cfg.seed + 1000 * run + r
            # The env draws its randomness (domain randomisation, when on) from torch's global RNG, which
            # this torch seeds anew in every process: seed it here (restoring the caller's afterwards) so
            # `evaluate.seed` decides. ψ needs no seed: the evaluation env sweeps the samples.
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed)
                env = make_env(subset, num_envs, seed)
                records = rollout(env, policy, per_env, data.num_keyframes)
            per_range[name] = [episode_metrics(rec, eval_cfg.success_threshold_m, reach)
                               for rec in records[: eval_cfg.episodes_per_range]]
        runs.append(per_range)
    return EvaluationResult(runs, {k: [list(map(float, i)) for i in v[0]] for k, v in ranges.items()})


def spread_in_ranges(psi_ranges: dict[str, list], names, per_range: int) -> list[tuple[str, float]]:
    """`per_range` ψ values spread inside each named range (interior points of its intervals)."""
    out = []
    for name in names:
        intervals = psi_ranges[name]
        total = sum(hi - lo for lo, hi in intervals)
        for j in range(per_range):
            target = total * (j + 0.5) / per_range
            for lo, hi in intervals:
                if target <= hi - lo + 1e-12:
                    out.append((name, float(lo + target)))
                    break
                target -= hi - lo
    return out


def trace_episode(policy: PolicyRunner, data: TrackingData, psi: float, make_env: Callable) -> EpisodeRecord:
    """One episode at the sample nearest ψ (one world)."""
    env = make_env(nearest_sample_data(data, psi), 1, 0)
    return rollout(env, policy, 1, data.num_keyframes)[0]
