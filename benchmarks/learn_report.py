"""How benchmarks/learn_cpu.py (and compare_trainers.py) score a trained policy: the evaluate stage's metrics from
t = 0, success by ψ bin and by the paper's ranges, keyframe by keyframe, and the tail of checkpoints with their
weight averages."""

from __future__ import annotations

from pathlib import Path


def evaluate_from_start(policy_dir: Path, data, env_cfg, episodes: int = 128) -> tuple[dict, list]:
    """The evaluate stage's metrics on the trained ψ range: deterministic policy, episodes from t = 0
    over the whole segment, no randomisation, success = every keyframe within 1 m. Also returns the
    per-episode metrics."""
    from pipeline.evaluation.config import EvalConfig
    from pipeline.evaluation.evaluate import PolicyRunner, default_env_factory, evaluate_policy
    from pipeline.evaluation.metrics import aggregate
    from pipeline.rl.checkpoint import load_policy

    module, _ = load_policy(policy_dir)
    eval_cfg = EvalConfig(episodes_per_range=episodes, runs=1, num_envs=min(episodes, 32), ranges=("train",))
    result = evaluate_policy(PolicyRunner(module), data, eval_cfg, default_env_factory(env_cfg, eval_cfg))
    per_episode = result.runs[0]["train"]
    return aggregate(per_episode), per_episode


def average_weights(snapshots: list[Path], out: Path) -> Path:
    """A policy directory holding the weight mean over `snapshots` (train.average_tail's mean, post hoc)."""
    import shutil

    from safetensors.torch import load_file, save_file

    from pipeline.rl.averaging import WeightAverage

    average = WeightAverage()
    for path in snapshots:
        average.add(load_file(path / "model.safetensors"))
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(snapshots[-1] / "config.json", out / "config.json")
    save_file(average.mean(), out / "model.safetensors")
    return out


def evaluate_snapshots(run_dir: Path, count: int, data, env_cfg) -> None:
    snapshots = sorted((run_dir / "checkpoints").glob("iter_*"))[-count:]
    print(f"[learn_cpu] the last {len(snapshots)} checkpoints, and their weight averages, on the same episodes:")
    sizes = [k for k in range(3, len(snapshots), 2)] + [len(snapshots)] if len(snapshots) > 1 else []
    candidates = [(path.name, path) for path in snapshots]
    candidates += [(f"mean of last {k}", average_weights(snapshots[-k:], run_dir / "averaged" / f"last_{k}")) for k in sizes]
    for label, path in candidates:
        ev, episodes = evaluate_from_start(path, data, env_cfg)
        print(f"[learn_cpu]   {label}: success {ev['success'] / 100:.3f} | {success_by_psi(episodes)}", flush=True)


def success_by_psi(episodes: list, bins: int = 6) -> str:
    """`0.20-0.50 1.00 (n=21, reached 0.76) | ...`: where in the ψ range the policy succeeds, and the mean ψ its
    episodes reached there (PsiReach: where the robot was at the landing keyframe), which says how closely its jump
    follows the ψ it is asked for."""
    import numpy as np

    from pipeline.evaluation.metrics import bin_by_psi

    psi = [e.psi for e in episodes]
    rows = bin_by_psi(episodes, np.linspace(min(psi), max(psi), bins + 1))
    return " | ".join(f"{r['psi_lo']:.2f}-{r['psi_hi']:.2f} {r['success'] / 100:.2f} (n={r['episodes']}, "
                      f"reached {r['psi_reached']:.2f})" for r in rows if r["episodes"] > 0)


def success_by_range(episodes: list, psi_ranges: dict) -> str:
    """`easy [0.7, 1.6] 0.62 (n=64) | hard ...`: success on the task's evaluation ranges."""
    import numpy as np

    from pipeline.evaluation.evaluate import range_mask

    psi = np.array([e.psi for e in episodes])
    success = np.array([bool(e.success) for e in episodes])
    cells = []
    for name in ("easy", "hard"):
        intervals = psi_ranges.get(name)
        if not intervals:
            continue
        mask = range_mask(psi, intervals)
        where = " ∪ ".join(f"[{lo:g}, {hi:g}]" for lo, hi in intervals)
        rate = f"{success[mask].mean():.2f}" if mask.any() else "-"
        cells.append(f"{name} {where} {rate} (n={int(mask.sum())})")
    return " | ".join(cells)


def report(label: str, ev: dict, episodes: list, data) -> None:
    from pipeline.evaluation.metrics import endings
    from pipeline.evaluation.report import endings_line

    print(f"[learn_cpu] {label}: success {ev['success'] / 100:.3f}, E_g-bpe {ev['e_g_bpe']:.0f} mm, "
          f"E_l-bpe {ev['e_l_bpe']:.0f} mm, ψ reached {ev['psi_reached']:.2f} m (largest by a successful "
          f"episode {ev['psi_reached_max']:.2f} m; clip {data.psi_raw:.2f} m)")
    print(f"[learn_cpu]   by ψ (m): {success_by_psi(episodes)}")
    print(f"[learn_cpu]   by the paper's ranges: {success_by_range(episodes, data.psi_ranges)}")
    print(f"[learn_cpu]   keyframe by keyframe, % reached (mean error mm): {funnel_line(episodes, data)}")
    print(f"[learn_cpu]   {endings_line(endings(episodes))}")


def funnel_line(episodes: list, data) -> str:
    """`0.10 100 (12) | 0.40 100 (30) | ... | 1.48 landing 62 (310)`: where the episodes are lost."""
    from pipeline.evaluation.metrics import SUCCESS_THRESHOLD_M
    from pipeline.evaluation.run import funnel_rows

    rows = funnel_rows(episodes, data, SUCCESS_THRESHOLD_M)
    return " | ".join(f"{r['time_s']:.2f}{' ' + r['label'] if r['label'] else ''} {r['reached']:.0f} "
                      f"({r['e_g_bpe']:.0f})" for r in rows)
