"""Evaluation outputs: metrics json (DVC metrics), per-ψ csv/json (DVC plots), figures, the table.

The table follows the paper's layout: one row per variant; column groups easy / hard / overall,
each with success, E_l-bpe, E_g-bpe, E_smth as "mean ± std" over runs.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from pipeline.common.atomic import atomic_file, write_text_atomic
from pipeline.common.errors import PipelineInputError
from pipeline.evaluation.metrics import (
    METRIC_LABELS,
    METRIC_NAMES,
    REACH_NAMES,
    EpisodeMetrics,
    EpisodeRecord,
    aggregate_ranges,
    bin_by_psi,
    pooled_episodes,
)
from pipeline.evaluation.paper import FIGURES, paper_section

RANGE_ORDER = ("easy", "hard", "overall")


def metrics_document(task: str, variant: str, runs: list[dict[str, list[EpisodeMetrics]]],
                     psi_ranges: dict, extra: dict | None = None) -> dict:
    return {"task": task, "variant": variant, "psi_ranges": psi_ranges,
            "ranges": aggregate_ranges(runs), **(extra or {})}


def write_metrics(path: str | Path, doc: dict) -> None:
    write_text_atomic(path, json.dumps(doc, indent=2, allow_nan=True))


def per_psi_rows(runs: list[dict[str, list[EpisodeMetrics]]], psi_ranges: dict, points: int) -> list[dict]:
    """Metrics in `points` equal ψ bins over the union of the ranges, all runs pooled."""
    episodes = pooled_episodes(runs)
    lo = min(i[0] for v in psi_ranges.values() for i in v)
    hi = max(i[1] for v in psi_ranges.values() for i in v)
    rows = bin_by_psi(episodes, np.linspace(lo, hi, points + 1))
    return [r for r in rows if r["episodes"] > 0]


def write_per_psi(csv_path: str | Path, rows: list[dict], json_path: str | Path | None = None) -> None:
    columns = ["psi", "psi_lo", "psi_hi", *METRIC_NAMES, *REACH_NAMES, "episodes"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{row[k]:.6g}" if isinstance(row[k], float) else row[k]) for k in columns})
    write_text_atomic(csv_path, buf.getvalue())
    if json_path is not None:
        write_text_atomic(json_path, json.dumps(rows, indent=1))


def _savefig(fig, path: Path) -> None:
    with atomic_file(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=110, bbox_inches="tight")


def plot_per_psi(rows_by_variant: dict[str, list[dict]], psi_ranges: dict, path: str | Path) -> None:
    """Success and the three errors against ψ, one line per variant, ranges shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.4))
    colors = {"easy": "#d8f0d8", "hard": "#f6dcdc"}
    for ax, metric in zip(axes, METRIC_NAMES):
        for name, intervals in psi_ranges.items():
            for lo, hi in intervals:
                ax.axvspan(lo, hi, color=colors.get(name, "#eeeeee"), zorder=0)
        for variant, rows in rows_by_variant.items():
            ax.plot([r["psi"] for r in rows], [r[metric] for r in rows], "o-", ms=3, label=variant)
        ax.set_xlabel("ψ (m)")
        ax.set_title(METRIC_LABELS[metric])
        ax.grid(alpha=0.3)
    axes[0].set_ylim(-2, 102)
    axes[0].legend(fontsize=7)
    _savefig(fig, Path(path))
    plt.close(fig)


def plot_adapters(traces: list[EpisodeRecord], phase_rate: float, path: str | Path) -> None:
    """The adapters' behaviour (paper's figure): phase interval Δφ = Δφ₀ + Δφ^Δ and the adapter's
    action magnitude over the episode, one line per ψ."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 3.6))
    for rec in traces:
        t = np.arange(rec.num_steps) * 0.02
        a0.plot(t, phase_rate + np.asarray(rec.phase_rate_offset), label=f"ψ={rec.psi:.2f}")
        if rec.adapter_action_norm is not None and np.isfinite(rec.adapter_action_norm).any():
            a1.plot(t, rec.adapter_action_norm, label=f"ψ={rec.psi:.2f}")
        for ax in (a0, a1):
            for k in np.flatnonzero(rec.keyframe_crossed):
                ax.axvline(t[k], color="gray", lw=0.5, alpha=0.4)
    a0.axhline(phase_rate, color="k", ls="--", lw=0.8, label="Δφ (stage 1)")
    a0.set_title("phase interval Δφ per step")
    a1.set_title("adapter action magnitude ‖a − a₁‖")
    for ax in (a0, a1):
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    _savefig(fig, Path(path))
    plt.close(fig)


def _cell(stat: dict, metric: str) -> str:
    m, s = stat["mean"], stat["std"]
    if not np.isfinite(m):
        return "–"
    digits = 1 if metric in ("success", "e_l_bpe", "e_g_bpe") else 2
    return f"{m:.{digits}f} ± {s:.{digits}f}"


def _reach_line(doc: dict) -> str:
    cells = []
    for g in RANGE_ORDER:
        r = doc["ranges"].get(g, {})
        mean, best = r.get("psi_reached", {}).get("mean", np.nan), r.get("psi_reached_max", {}).get("mean", np.nan)
        if np.isfinite(mean):
            cells.append(f"{g} {mean:.2f} / " + (f"{best:.2f}" if np.isfinite(best) else "–"))
    return ", ".join(cells)


def results_table(docs: dict[str, dict]) -> str:
    """Markdown table in the paper's layout from {variant: metrics json}."""
    short = {"success": "Succ.↑", "e_l_bpe": "E_l-bpe↓", "e_g_bpe": "E_g-bpe↓", "e_smth": "E_smth↓"}
    groups = [g for g in RANGE_ORDER if any(g in d["ranges"] for d in docs.values())]
    head1 = "| Method | " + " | ".join(f"{g} {short[m]}" for g in groups for m in METRIC_NAMES) + " |"
    sep = "|---|" + "---|" * (len(groups) * len(METRIC_NAMES))
    lines = [head1, sep]
    for variant, doc in docs.items():
        cells = [_cell(doc["ranges"][g][m], m) if g in doc["ranges"] else "–" for g in groups for m in METRIC_NAMES]
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    note = ("\nSucc. in %, E_l-bpe and E_g-bpe in mm, E_smth in rad/s²; mean ± std over runs "
            f"({next(iter(docs.values()))['ranges']['overall']['episodes']['runs']} runs, seeded differently; every run "
            "meets the same ψ samples, so runs differ only where domain randomisation or a sampling policy is "
            "on).\n") if docs else ""
    reach_lines = {variant: _reach_line(doc) for variant, doc in docs.items()}
    reach = [f"- {variant}: {line}" for variant, line in reach_lines.items() if line]
    if reach:
        note += ("\nψ reached (the task variable achieved, from where the robot was at the edited keyframe; "
                 "mean over all episodes / farthest by a successful one; the clip's own ψ_raw "
                 f"{next(iter(docs.values())).get('psi_raw', float('nan')):.2f}):\n" + "\n".join(reach) + "\n")
    funnels = [funnel_table(variant, doc["keyframe_funnel"]) + (f"\n{endings_line(doc['endings'])}\n" if doc.get("endings") else "")
               for variant, doc in docs.items() if doc.get("keyframe_funnel")]
    return "\n".join(lines) + "\n" + note + "".join(funnels)


def rest_to_rest_table(docs: dict[str, dict], randomised: dict[str, dict]) -> str:
    """Markdown: the chain from the stance at rest (export/chain.py), per variant and range: `rest_to_rest` and
    its parts (the paper's success on the task stretch, standing after it), nominal and under the paper's
    domain randomisation (metrics_dr.json). Empty when no variant was evaluated as a chain."""
    chained = {v: d for v, d in docs.items() if "rest_to_rest" in d["ranges"].get("overall", {})}
    if not chained:
        return ""
    groups = [g for g in RANGE_ORDER if any(g in d["ranges"] for d in chained.values())]
    lines = ["\n## From rest to rest\n",
             "The chain a robot runs: the balance policy holds the stance at rest, the task policy runs on the go, the "
             "balance policy takes over when the task's phase ends. `rest_to_rest` (%): every keyframe within 1 m and "
             "standing 3 s after the handoff (|g_xy| < 0.3, pelvis ≥ 0.55 m above the ground, on the ground the "
             "reference ends on, base speed < 0.2 m/s, no fall before); in brackets the task stretch's success / "
             "standing. DR: under the paper's domain randomisation.\n",
             "| Method | " + " | ".join(f"{g} rest_to_rest" for g in groups) + " | " +
             " | ".join(f"{g} DR" for g in groups) + " |", "|---|" + "---|" * (2 * len(groups))]

    def cell(doc: dict | None, g: str) -> str:
        r = (doc or {}).get("ranges", {}).get(g, {})
        if "rest_to_rest" not in r:
            return "–"
        success = r.get("chain_success", r.get("success", {})).get("mean", float("nan"))  # metrics_dr.json: the chain's own
        return f"{r['rest_to_rest']['mean']:.1f} ({success:.0f} / {r.get('standing', {}).get('mean', float('nan')):.0f})"

    endings = []  # below the table: a line between its rows would end it
    for variant, doc in chained.items():
        lines.append(f"| {variant} | " + " | ".join(cell(doc, g) for g in groups) + " | " +
                     " | ".join(cell(randomised.get(variant), g) for g in groups) + " |")
        ended = doc.get("chain", {}).get("endings")
        if ended:
            endings.append(f"\n{variant}, where the chains ended (stretch:check, episodes): " +
                           ", ".join(f"{k} {v}" for k, v in ended.items()))
    return "\n".join(lines + endings) + "\n"


def funnel_table(variant: str, rows: list[dict]) -> str:
    """Markdown: where the variant's episodes end, keyframe by keyframe (run.funnel_rows)."""
    lines = [f"\n## {variant}: keyframe by keyframe\n",
             "Of all evaluated episodes: % that reached the keyframe (the rest had fallen), % that reached it with "
             "every keyframe so far within the success threshold, and the mean body error there.\n",
             "| keyframe | time (s) | reached (%) | on track (%) | E_g-bpe (mm) |", "|---|---|---|---|---|"]
    for r in rows:
        name = f"{r['keyframe']}" + (f" {r['label']}" if r.get("label") else "")
        err = f"{r['e_g_bpe']:.0f}" if np.isfinite(r["e_g_bpe"]) else "–"
        lines.append(f"| {name} | {r['time_s']:.2f} | {r['reached']:.1f} | {r['on_track']:.1f} | {err} |")
    return "\n".join(lines) + "\n"


def endings_line(doc: dict) -> str:
    """`How the 384 episodes ended: 9 % ran to the end; 41 % fell forward, ... Checks that ended them: ...`
    from metrics.endings."""
    ending, check = doc["ending"], doc["check"]
    falls = [f"{ending[name]:.0f} % {label}" for name, label in
             (("forward", "fell forward"), ("backward", "fell backward"), ("sideways", "fell sideways"),
              ("sank", "sank (upright against the reference)"), ("unknown", "ended in a way not recorded"))
             if ending.get(name, 0.0) > 0.0]
    fired = [f"{label} {check[name]:.0f} %" for name, label in
             (("tilt", "tilt"), ("base_height", "base height"), ("keyframe_error", "keyframe error"))
             if check.get(name, 0.0) > 0.0]
    line = f"How the {doc['episodes']} episodes ended: {ending['completed']:.0f} % ran to the end"
    line += ("; " + ", ".join(falls) + ".") if falls else "."
    if fired:
        line += " Checks that ended them: " + ", ".join(fired) + "."
    return line


def seed_summary(docs_by_seed: dict[int, dict]) -> dict:
    """Success over training seeds, per range: each seed's success (its metrics' mean over evaluation
    runs), their mean, sample std (ddof 1; null for one seed), min and max; and each seed's E_g-bpe (mm)
    and their mean where every seed's metrics have it. From {seed: metrics json}."""
    seeds = list(docs_by_seed)
    ranges = [g for g in RANGE_ORDER if all(g in d["ranges"] for d in docs_by_seed.values())]
    out: dict = {"seeds": seeds, "ranges": {}}
    for g in ranges:
        values = np.array([docs_by_seed[s]["ranges"][g]["success"]["mean"] for s in seeds], dtype=np.float64)
        out["ranges"][g] = {
            "success_per_seed": {str(s): float(v) for s, v in zip(seeds, values)},
            "success_mean": float(values.mean()),
            "success_std": float(values.std(ddof=1)) if len(values) > 1 else None,
            "success_min": float(values.min()),
            "success_max": float(values.max()),
        }
        # the body error decides two of the paper's claims, so its spread over seeds goes beside success's
        errors = [docs_by_seed[s]["ranges"][g].get("e_g_bpe", {}).get("mean") for s in seeds]
        if all(e is not None for e in errors):
            out["ranges"][g]["e_g_bpe_per_seed"] = {str(s): float(e) for s, e in zip(seeds, errors)}
            out["ranges"][g]["e_g_bpe_mean"] = float(np.mean(errors))
    return out


def seeds_table(summaries: dict[str, dict], heading: str = "##", unseeded: list[str] | tuple = ()) -> str:
    """Markdown: success (%) per training seed and over them, one row per variant, from seed_summary; the
    `unseeded` variants (trained at the first seed only) named below it."""
    if not summaries:
        return ""
    seeds = next(iter(summaries.values()))["seeds"]
    groups = [g for g in RANGE_ORDER if any(g in s["ranges"] for s in summaries.values())]
    lines = [f"\n{heading} Success over training seeds ({len(seeds)}: {', '.join(map(str, seeds))})\n",
             "Each seed trains stage 1 + 2 from scratch with everything else equal, and is evaluated as above. "
             "The table above is the first seed's policy alone; how far it moves from seed to seed is here: "
             "mean ± sample std over seeds [min–max], then each seed's success (%) and overall E_g-bpe (mm).\n",
             "| Method | " + " | ".join(f"{g} Succ. over seeds" for g in groups) + " | overall E_g-bpe over seeds "
             "| per seed (" + " / ".join(groups) + "; E_g-bpe) |",
             "|---|" + "---|" * (len(groups) + 2)]
    for variant, summary in summaries.items():
        cells = []
        for g in groups:
            r = summary["ranges"].get(g)
            if r is None:
                cells.append("–")
                continue
            std = "–" if r["success_std"] is None else f"{r['success_std']:.1f}"
            cells.append(f"{r['success_mean']:.1f} ± {std} [{r['success_min']:.1f}–{r['success_max']:.1f}]")
        errors = summary["ranges"].get("overall", {}).get("e_g_bpe_per_seed")
        error_cell = "–" if errors is None else (f"{summary['ranges']['overall']['e_g_bpe_mean']:.1f} "
                                                 f"[{min(errors.values()):.1f}–{max(errors.values()):.1f}]")
        per_seed = "; ".join(f"seed {s}: " + " / ".join(f"{summary['ranges'][g]['success_per_seed'][str(s)]:.1f}"
                                                      for g in groups if g in summary["ranges"])
                             + ("" if errors is None else f", {errors[str(s)]:.1f} mm")
                             for s in summary["seeds"])
        lines.append(f"| {variant} | " + " | ".join(cells) + f" | {error_cell} | {per_seed} |")
    if unseeded:
        lines.append(f"\nThe other rows are trained at the first seed only: {', '.join(unseeded)} (`seed_variants`).")
    return "\n".join(lines) + "\n"


def _load_metrics(path: Path, what: str) -> dict:
    if not path.is_file():
        raise PipelineInputError(path, None, f"no evaluation for {what}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise PipelineInputError(path, None, f"malformed JSON: {err}") from None


def write_report(task: str, variants: list[str], results_dir: str | Path, out_dir: str | Path,
                 seeds: tuple[int, ...] | list[int] = (), figures: str | Path = FIGURES,
                 seed_variants: list[str] | None = None) -> Path:
    """reports/<task>/: table.md over the variants evaluated (then the rest-to-rest chains, the spread over
    training seeds, and the paper's rows and claims from `figures`, evaluation/paper.py), per-ψ figure of all
    variants, and seeds.json: success over the training `seeds` (the first is the main run's train.seed, in
    results/<task>/<variant>/; the others in results/<task>/<variant>/seeds/<seed>/), for the
    `seed_variants` (all of `variants` when None)."""
    results_dir, out_dir = Path(results_dir), Path(out_dir)
    docs, rows, ranges, summaries = {}, {}, {}, {}
    for variant in variants:
        docs[variant] = _load_metrics(results_dir / variant / "metrics.json",
                                      f"variant {variant!r} (run the evaluate stage)")
        ranges = docs[variant].get("psi_ranges", ranges)
        per_psi = results_dir / variant / "per_psi.json"
        if per_psi.is_file():
            rows[variant] = json.loads(per_psi.read_text())
        if seeds and (seed_variants is None or variant in seed_variants):
            by_seed = {seeds[0]: docs[variant]}
            for seed in seeds[1:]:
                by_seed[seed] = _load_metrics(results_dir / variant / "seeds" / str(seed) / "metrics.json",
                                              f"variant {variant!r} at training seed {seed} (run evaluate_seed)")
            summaries[variant] = seed_summary(by_seed)
    randomised = {v: json.loads((results_dir / v / "metrics_dr.json").read_text()) for v in variants
                  if (results_dir / v / "metrics_dr.json").is_file()}
    out_dir.mkdir(parents=True, exist_ok=True)
    table = (f"# {task}\n\n" + results_table(docs) + rest_to_rest_table(docs, randomised)
             + (seeds_table(summaries, unseeded=[v for v in variants if v not in summaries])
                if len(seeds) > 1 and summaries else "") + paper_section(docs, figures))
    write_text_atomic(out_dir / "table.md", table)
    if summaries:
        write_text_atomic(out_dir / "seeds.json", json.dumps(summaries, indent=1))
    if rows:
        plot_per_psi(rows, ranges, out_dir / "per_psi.png")
    return out_dir / "table.md"
