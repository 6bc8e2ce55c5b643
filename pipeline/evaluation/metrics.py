"""The paper's evaluation metrics, as pure functions of recorded trajectories (numpy only).

Definitions (AdaMimic, "Evaluation metrics"):
  * success: an episode fails if the mean distance error over the tracked bodies exceeds 1 m at
    any keyframe. An episode that ends (falls, is terminated) before crossing all its keyframes
    never reached them, so it fails too.
  * E_g-bpe (mm): world-frame body position error averaged over bodies and keyframe phases.
  * E_l-bpe (mm): root-frame body position error averaged over bodies and all steps.
  * E_smth (rad/s^2): mean absolute joint acceleration over the episode.
Not in the paper: ψ reached (`PsiReach`), the task variable the robot actually achieved, e.g. how far
a far jump landed; per range its mean and the farthest a successful episode reached. And the keyframe
funnel (`keyframe_funnel`): how many episodes reached each keyframe and were still on track there,
which says where a policy that fails loses its episodes (a fall after the landing, a missed take-off), and the
endings (`endings`): how they were lost (ran to the end, or fell forward, backward, sideways or sank, and which
of the env's checks ended them).

Errors are pooled: over a set of episodes, E_g-bpe is the mean over every (episode, keyframe,
body) sample, E_l-bpe over every (episode, step, body) sample, E_smth over every (episode, step,
joint) sample. Each episode therefore keeps sums and counts (`EpisodeMetrics`) so that
aggregation over any grouping (ψ range, ψ bin) is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SUCCESS_THRESHOLD_M = 1.0
METRIC_NAMES = ("success", "e_l_bpe", "e_g_bpe", "e_smth")
REACH_NAMES = ("psi_reached", "psi_reached_max")  # the task variable achieved (PsiReach), not in the paper's table
METRIC_LABELS = {
    "success": "Succ. (%)",
    "e_l_bpe": "E_l-bpe (mm)",
    "e_g_bpe": "E_g-bpe (mm)",
    "e_smth": "E_smth (rad/s²)",
}


@dataclass
class EpisodeRecord:
    """What one evaluation episode recorded, one row per control step.

    body_error_world: (T, B) distance (m) of each tracked body to its global target, world frame.
    body_error_local: (T, B) distance (m) of each tracked body to its target, root frame.
    keyframe_crossed: (T,) bool, True on the step whose phase crossed a keyframe.
    joint_acc: (T, J) joint accelerations (rad/s^2).
    psi: the episode's task variable; num_keyframes: how many keyframes the episode should cross.
    phase, phase_rate_offset, adapter_action_norm: optional (T,) traces for the adapter figure.
    """

    body_error_world: np.ndarray
    body_error_local: np.ndarray
    keyframe_crossed: np.ndarray
    joint_acc: np.ndarray
    psi: float
    num_keyframes: int
    phase: np.ndarray | None = None
    phase_rate_offset: np.ndarray | None = None
    adapter_action_norm: np.ndarray | None = None
    keyframe_miss: np.ndarray | None = None  # (T, 3) mean body position − keyframe target on crossing rows
    # The env's checks that ended the episode (info["terminated_by"]): () when it ran to the motion's end,
    # None when not known (an env that does not say, or a rollout cut short by its step limit).
    ended_by: tuple[str, ...] | None = None
    end_tilt_error: np.ndarray | None = None  # (2,) info["tilt_error_xy"] on the last step
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.body_error_world = np.asarray(self.body_error_world, dtype=np.float64)
        self.body_error_local = np.asarray(self.body_error_local, dtype=np.float64)
        self.keyframe_crossed = np.asarray(self.keyframe_crossed, dtype=bool).reshape(-1)
        if self.keyframe_miss is not None:
            self.keyframe_miss = np.asarray(self.keyframe_miss, dtype=np.float64).reshape(-1, 3)
        self.joint_acc = np.asarray(self.joint_acc, dtype=np.float64)
        t = self.keyframe_crossed.shape[0]
        for name in ("body_error_world", "body_error_local", "joint_acc"):
            arr = getattr(self, name)
            if arr.ndim != 2 or arr.shape[0] != t:
                raise ValueError(f"EpisodeRecord.{name}: expected ({t}, n), got {arr.shape}")

    @property
    def num_steps(self) -> int:
        return int(self.keyframe_crossed.shape[0])


@dataclass(frozen=True)
class EpisodeMetrics:
    """Per-episode success plus sums and counts of each pooled error."""

    psi: float
    success: bool
    global_error_sum: float  # m, over (keyframe, body) samples
    global_error_count: int
    local_error_sum: float  # m, over (step, body) samples
    local_error_count: int
    joint_acc_abs_sum: float  # rad/s^2, over (step, joint) samples
    joint_acc_count: int
    psi_reached: float = float("nan")  # see PsiReach; nan when not measurable
    keyframe_errors: tuple[float, ...] = ()  # body-mean world error (m) at each keyframe crossed, in order
    ending: str = "unknown"  # one of ENDINGS (`classify_ending`)
    ended_by: tuple[str, ...] = ()  # the env's checks that ended it


# How an episode ended: it ran to the motion's end, or a fall check ended it, and then which way the pelvis
# had tipped against the reference's (or not: it sank, knees folding or sitting down, while still upright).
ENDINGS = ("completed", "forward", "backward", "sideways", "sank", "unknown")
SANK_TILT = 0.3  # |tilt error| below this (about 17° past the reference's lean) is not a tip-over


def classify_ending(ended_by: tuple[str, ...] | None, tilt_error: np.ndarray | None) -> str:
    """One of ENDINGS from the checks that ended an episode and its last tilt error against the reference
    (x + forward, y + left, in the pelvis frame)."""
    if ended_by is None:
        return "unknown"
    if not ended_by:
        return "completed"
    if tilt_error is None:
        return "unknown"
    ex, ey = (float(v) for v in tilt_error)
    if math.hypot(ex, ey) < SANK_TILT:
        return "sank"
    if abs(ey) > abs(ex):
        return "sideways"
    return "forward" if ex > 0 else "backward"


def keyframe_mean_errors(body_error_world: np.ndarray, keyframe_crossed: np.ndarray) -> np.ndarray:
    """(K_crossed,) mean over bodies of the world error on each keyframe-crossing step."""
    err = np.asarray(body_error_world, dtype=np.float64)
    crossed = np.asarray(keyframe_crossed, dtype=bool).reshape(-1)
    return err[crossed].mean(axis=1) if crossed.any() else np.zeros(0)


def episode_success(body_error_world, keyframe_crossed, num_keyframes: int,
                    threshold: float = SUCCESS_THRESHOLD_M) -> bool:
    """True when every keyframe was reached and none had a body-mean world error above `threshold`."""
    per_keyframe = keyframe_mean_errors(body_error_world, keyframe_crossed)
    if per_keyframe.shape[0] < num_keyframes:
        return False
    return bool(np.all(per_keyframe <= threshold))


@dataclass(frozen=True)
class PsiReach:
    """The ψ an episode actually reached, read off where the robot was at the edited keyframe.

    Editing moves keyframe k's target linearly in ψ along one axis (far jump: the landing along x by
    ψ − ψ_raw; high jump: the apex along z), fitted here on the dataset's samples. An episode that
    misses the target by m along that axis reached ψ + m / slope: a far jump landing 0.2 m short of
    its 1.5 m target reached 1.3 m, and one that never left the ground reached about 0. Non-linear
    edits (heading) or tasks without edits have no PsiReach (`fit` returns None).
    """

    keyframe: int  # the keyframe whose target moves most with ψ (the first of equals: the landing)
    axis: np.ndarray  # (3,) unit direction it moves in
    slope: float  # metres per unit of ψ

    @staticmethod
    def fit(psi: np.ndarray, keyframe_offsets: np.ndarray, min_r2: float = 0.999) -> "PsiReach | None":
        psi = np.asarray(psi, dtype=np.float64)
        offsets = np.asarray(keyframe_offsets, dtype=np.float64)  # (N, K, 3)
        if psi.shape[0] < 2 or np.ptp(psi) <= 0:
            return None
        dpsi = psi - psi.mean()
        doff = offsets - offsets.mean(axis=0)
        slopes = np.einsum("n,nkc->kc", dpsi, doff) / float(dpsi @ dpsi)  # (K, 3) least squares
        norms = np.linalg.norm(slopes, axis=-1)
        k = int(np.argmax(norms >= norms.max() * (1 - 1e-6)))
        if norms[k] < 1e-9:
            return None
        residual = doff[:, k] - dpsi[:, None] * slopes[k]
        total = float((doff[:, k] ** 2).sum())
        if total <= 0 or 1.0 - float((residual**2).sum()) / total < min_r2:
            return None
        return PsiReach(keyframe=k, axis=slopes[k] / norms[k], slope=float(norms[k]))

    def reached(self, psi: float, keyframe_misses: np.ndarray) -> float:
        """`keyframe_misses`: (K_crossed, 3) miss vectors in crossing order (episodes from t = 0)."""
        if keyframe_misses.shape[0] <= self.keyframe or not np.all(np.isfinite(keyframe_misses[self.keyframe])):
            return float("nan")
        return float(psi + keyframe_misses[self.keyframe] @ self.axis / self.slope)


def episode_metrics(record: EpisodeRecord, threshold: float = SUCCESS_THRESHOLD_M,
                    reach: PsiReach | None = None) -> EpisodeMetrics:
    crossed = record.keyframe_crossed
    at_keyframes = record.body_error_world[crossed]
    reached = float("nan")
    if reach is not None and record.keyframe_miss is not None:
        reached = reach.reached(float(record.psi), record.keyframe_miss[crossed])
    return EpisodeMetrics(
        psi=float(record.psi),
        success=episode_success(record.body_error_world, crossed, record.num_keyframes, threshold),
        global_error_sum=float(at_keyframes.sum()),
        global_error_count=int(at_keyframes.size),
        local_error_sum=float(record.body_error_local.sum()),
        local_error_count=int(record.body_error_local.size),
        joint_acc_abs_sum=float(np.abs(record.joint_acc).sum()),
        joint_acc_count=int(record.joint_acc.size),
        psi_reached=reached,
        keyframe_errors=tuple(float(e) for e in keyframe_mean_errors(record.body_error_world, crossed)),
        ending=classify_ending(record.ended_by, record.end_tilt_error),
        ended_by=tuple(record.ended_by or ()),
    )


def keyframe_funnel(episodes: list[EpisodeMetrics], num_keyframes: int,
                    threshold: float = SUCCESS_THRESHOLD_M) -> list[dict[str, float]]:
    """Per keyframe k: `reached` (% of the episodes that crossed it: the others had fallen before),
    `on_track` (% that crossed it and every keyframe up to it within `threshold`, so on_track at the
    last keyframe is the success rate) and `e_g_bpe` (mm, mean error at k over the episodes that
    reached it)."""
    rows = []
    n = len(episodes)
    for k in range(num_keyframes):
        at_k = [e.keyframe_errors[k] for e in episodes if len(e.keyframe_errors) > k]
        on_track = sum(1 for e in episodes if len(e.keyframe_errors) > k and max(e.keyframe_errors[: k + 1]) <= threshold)
        rows.append({"keyframe": k, "reached": 100.0 * _ratio(len(at_k), n), "on_track": 100.0 * _ratio(on_track, n),
                     "e_g_bpe": 1000.0 * float(np.mean(at_k)) if at_k else float("nan")})
    return rows


def endings(episodes: list[EpisodeMetrics], checks=("tilt", "base_height", "keyframe_error")) -> dict:
    """% of `episodes` per ending (ENDINGS) and % ended by each of the env's `checks` (several can fire on
    one step, so those may add up to more than the falls)."""
    n = len(episodes)
    return {"ending": {name: 100.0 * _ratio(sum(e.ending == name for e in episodes), n) for name in ENDINGS},
            "check": {name: 100.0 * _ratio(sum(name in e.ended_by for e in episodes), n) for name in checks},
            "episodes": n}


def _ratio(num: float, den: int) -> float:
    return float(num / den) if den > 0 else float("nan")


def aggregate(episodes: list[EpisodeMetrics]) -> dict[str, float]:
    """Success rate (%) and pooled errors (E_*-bpe in mm, E_smth in rad/s^2) over episodes."""
    if not episodes:
        return {name: float("nan") for name in METRIC_NAMES + REACH_NAMES} | {"episodes": 0}
    return {
        "success": 100.0 * float(np.mean([e.success for e in episodes])),
        "e_l_bpe": 1000.0 * _ratio(sum(e.local_error_sum for e in episodes),
                                   sum(e.local_error_count for e in episodes)),
        "e_g_bpe": 1000.0 * _ratio(sum(e.global_error_sum for e in episodes),
                                   sum(e.global_error_count for e in episodes)),
        "e_smth": _ratio(sum(e.joint_acc_abs_sum for e in episodes),
                         sum(e.joint_acc_count for e in episodes)),
        **_reach(episodes),
        "episodes": len(episodes),
    }


def _reach(episodes: list[EpisodeMetrics]) -> dict[str, float]:
    """psi_reached: mean ψ reached; psi_reached_max: the farthest reached by a successful episode."""
    reached = np.array([e.psi_reached for e in episodes], dtype=np.float64)
    ok = np.array([e.success for e in episodes], dtype=bool) & np.isfinite(reached)
    finite = reached[np.isfinite(reached)]
    return {"psi_reached": float(finite.mean()) if finite.size else float("nan"),
            "psi_reached_max": float(reached[ok].max()) if ok.any() else float("nan")}


def pooled_episodes(runs: list[dict[str, list[EpisodeMetrics]]]) -> list[EpisodeMetrics]:
    """Every episode of every run and range, in one list."""
    return [e for run in runs for name in run for e in run[name]]


def aggregate_ranges(runs: list[dict[str, list[EpisodeMetrics]]]) -> dict[str, dict[str, dict[str, float]]]:
    """Per range (easy, hard, and overall = their union) mean ± std over runs of each metric.

    `runs[r][range_name]` holds the episodes of run r in that range. Returns
    {range: {metric: {"mean": m, "std": s}}, ...} with std the population std over runs.
    """
    if not runs:
        raise ValueError("aggregate_ranges needs at least one run")
    ranges = list(runs[0])
    per_run: dict[str, list[dict[str, float]]] = {name: [] for name in ranges + ["overall"]}
    for run in runs:
        for name in ranges:
            per_run[name].append(aggregate(run[name]))
        per_run["overall"].append(aggregate([e for name in ranges for e in run[name]]))
    return {name: mean_std(values) for name, values in per_run.items()}


def mean_std(values: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Mean and (population) std over runs of each metric; `episodes` is summed."""
    out: dict[str, dict[str, float]] = {}
    for metric in METRIC_NAMES + REACH_NAMES:
        column = np.array([v[metric] for v in values], dtype=np.float64)
        finite = column[np.isfinite(column)]
        out[metric] = {
            "mean": float(finite.mean()) if finite.size else float("nan"),
            "std": float(finite.std()) if finite.size else float("nan"),
        }
    out["episodes"] = {"total": int(sum(v.get("episodes", 0) for v in values)), "runs": len(values)}
    return out


def bin_by_psi(episodes: list[EpisodeMetrics], edges: np.ndarray) -> list[dict[str, float]]:
    """Metrics per ψ bin [edges[i], edges[i+1]) (last bin closed): rows for plots vs ψ."""
    edges = np.asarray(edges, dtype=np.float64)
    psi = np.array([e.psi for e in episodes])
    rows = []
    for i in range(len(edges) - 1):
        lo, hi = edges[i], edges[i + 1]
        inside = (psi >= lo) & ((psi < hi) if i < len(edges) - 2 else (psi <= hi))
        row = aggregate([e for e, keep in zip(episodes, inside) if keep])
        rows.append({"psi": float(0.5 * (lo + hi)), "psi_lo": float(lo), "psi_hi": float(hi)} | row)
    return rows
