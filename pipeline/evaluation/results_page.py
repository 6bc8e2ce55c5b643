"""`docs/results.md`: every measured policy on one page, regenerated from what evaluation wrote.

    .venv/bin/python -m pipeline.evaluation.results_page [--root .] [--out docs/results.md]

Reads, for each task:
  results/<task>/<variant>/metrics.json, per_psi.csv     (the evaluate stage)
  results/<task>/<variant>/media/*.mp4                   (its rollout videos, when present)
  data/keyframes/<task>/keyframes.png                    (the keyframes stage's figure, when present;
                                                         a committed policy's own keyframes.png first)
  models/pretrained/<name>/[<variant>/]metrics.json      (committed policies; a folder without one is a recipe)
and writes docs/results.md with, per task, the table in the paper's layout, a success-vs-ψ plot, the keyframe
figure and a GIF of one rollout, the images under docs/img/results/<task>/.

The page holds no number that is not in those files, so it cannot drift from what was measured: rerun it
after `dvc repro`. Videos and keyframe figures are DVC outputs, not in git; where one is missing (a fresh
clone), the image made from it last time is kept, and the page says where it came from.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.common.atomic import write_text_atomic
from pipeline.common.errors import PipelineInputError
from pipeline.evaluation.metrics import METRIC_NAMES
from pipeline.evaluation.balance_section import balance_section, is_balance_policy, read_balance_metrics
from pipeline.evaluation.page_images import copy_keyframes_figure, plot_success_vs_psi, rollout_video, video_to_gif
from pipeline.evaluation.report import RANGE_ORDER, _cell, endings_line, rest_to_rest_table, seeds_table

PAPER_TITLE = "Towards Adaptable Humanoid Control via Adaptive Motion Tracking"
SHORT = {"success": "Succ.↑", "e_l_bpe": "E_l-bpe↓", "e_g_bpe": "E_g-bpe↓", "e_smth": "E_smth↓"}


@dataclass
class Evaluated:
    """One evaluated policy: a task × variant under results/, or a committed policy under models/pretrained/."""

    task: str
    variant: str
    folder: Path  # holds metrics.json (and per_psi.csv, media/)
    metrics: dict
    per_psi: list[dict] = field(default_factory=list)


@dataclass
class Recipe:
    """A models/pretrained/<name>/ folder with no measured policy yet."""

    name: str
    folder: Path


# ------------------------------------------------------------------------------------------ reading
def read_metrics(path: Path) -> dict:
    """A metrics.json of the evaluate stage, checked for what the page uses."""
    try:
        doc = json.loads(path.read_text())  # json accepts the NaN the evaluate stage writes
    except json.JSONDecodeError as error:
        raise PipelineInputError(path, None, f"not valid JSON ({error})") from None
    if not isinstance(doc, dict):
        raise PipelineInputError(path, None, "must be a JSON object")
    ranges = doc.get("ranges")
    if not isinstance(ranges, dict) or not ranges:
        raise PipelineInputError(path, "ranges", "missing or empty: not a metrics.json of the evaluate stage")
    for name, stats in ranges.items():
        for metric in METRIC_NAMES:
            stat = stats.get(metric) if isinstance(stats, dict) else None
            if not isinstance(stat, dict) or "mean" not in stat or "std" not in stat:
                raise PipelineInputError(path, f"ranges.{name}.{metric}", "missing its mean and std")
    if not isinstance(doc.get("psi_ranges"), dict):
        raise PipelineInputError(path, "psi_ranges", "missing: the task's ψ ranges")
    return doc


def read_seeds(path: Path) -> dict:
    """reports/<task>/seeds.json of the report stage, {variant: {seeds, ranges}}, checked for every field the
    page's seeds table reads."""
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise PipelineInputError(path, None, f"not valid JSON ({error})") from None
    if not isinstance(doc, dict) or not doc:
        raise PipelineInputError(path, None, "must be a non-empty JSON object, one entry per variant")
    for variant, summary in doc.items():
        if not isinstance(summary, dict) or not isinstance(summary.get("seeds"), list) or not summary["seeds"] \
                or not isinstance(summary.get("ranges"), dict):
            raise PipelineInputError(path, variant, "needs its `seeds` list and `ranges`")
        for name, stats in summary["ranges"].items():
            where = f"{variant}.ranges.{name}"
            per_seed = stats.get("success_per_seed") if isinstance(stats, dict) else None
            if not isinstance(per_seed, dict) or any(str(seed) not in per_seed for seed in summary["seeds"]):
                raise PipelineInputError(path, f"{where}.success_per_seed", "missing a seed's success")
            for key in ("success_mean", "success_min", "success_max"):
                if not isinstance(stats.get(key), (int, float)):
                    raise PipelineInputError(path, f"{where}.{key}", "missing or not a number")
            if stats.get("success_std") is not None and not isinstance(stats["success_std"], (int, float)):
                raise PipelineInputError(path, f"{where}.success_std", "not a number")
    return doc


def read_per_psi(path: Path) -> list[dict]:
    """per_psi.csv rows as floats: ψ bin centre and its success (%)."""
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        for column in ("psi", "success"):
            if column not in (reader.fieldnames or []):
                raise PipelineInputError(path, column, "missing column")
        rows = []
        for line, row in enumerate(reader, start=2):
            try:
                rows.append({key: float(value) for key, value in row.items() if value not in (None, "")})
            except ValueError:
                raise PipelineInputError(path, f"line {line}", "holds a value that is not a number") from None
    return rows


def _evaluated(folder: Path, task: str, variant: str, metrics: dict | None = None) -> Evaluated:
    metrics = read_metrics(folder / "metrics.json") if metrics is None else metrics
    csv_path = folder / "per_psi.csv"
    return Evaluated(task=task, variant=variant, folder=folder, metrics=metrics,
                     per_psi=read_per_psi(csv_path) if csv_path.is_file() else [])


@dataclass
class Found:
    """Everything the page reads, read and checked before anything is written."""

    results: list[Evaluated]  # under results/
    pretrained: list[Evaluated]  # under models/pretrained/
    recipes: list[Recipe]  # models/pretrained/ folders with no policy yet
    seeds: dict[str, dict]  # task -> reports/<task>/seeds.json (the spread over training seeds)
    balance: list[tuple[Path, dict]] = field(default_factory=list)  # (folder, metrics.json) of balance policies


def find_results(root: Path) -> Found:
    results = [_evaluated(path.parent, path.parent.parent.name, path.parent.name)
               for path in sorted((root / "results").glob("*/*/metrics.json"))]
    pretrained, recipes, balance = [], [], []
    for folder in sorted(p for p in (root / "models" / "pretrained").glob("*") if p.is_dir()):
        if is_balance_policy(folder):
            balance.append((folder, read_balance_metrics(folder / "metrics.json")))
            continue
        found = sorted(folder.glob("metrics.json")) + sorted(folder.glob("*/metrics.json"))
        if not found:
            recipes.append(Recipe(folder.name, folder))
        for path in found:
            doc = read_metrics(path)
            variant = doc.get("variant") or (path.parent.name if path.parent != folder else "adamimic")
            pretrained.append(_evaluated(path.parent, doc.get("task") or folder.name, variant, doc))
    seeds = {task: read_seeds(path) for task in sorted({e.task for e in results})
             if (path := root / "reports" / task / "seeds.json").is_file()}
    return Found(results, pretrained, recipes, seeds, balance)


def chain_balance(root: Path) -> Path | None:
    """The balance policy folder the chains use (params.yaml `balance.out`), None where the root has no params."""
    params = root / "params.yaml"
    if not params.is_file():
        return None
    import yaml

    out = ((yaml.safe_load(params.read_text()) or {}).get("balance") or {}).get("out")
    return (root / out).resolve() if out else None



# ------------------------------------------------------------------------------------------ page
def _table(entries: list[Evaluated]) -> list[str]:
    groups = [g for g in RANGE_ORDER if any(g in e.metrics["ranges"] for e in entries)]
    lines = ["| Method | " + " | ".join(f"{g} {SHORT[m]}" for g in groups for m in METRIC_NAMES) + " |",
             "|---|" + "---|" * (len(groups) * len(METRIC_NAMES))]
    for e in entries:
        cells = [_cell(e.metrics["ranges"][g][m], m) if g in e.metrics["ranges"] else "–"
                 for g in groups for m in METRIC_NAMES]
        lines.append(f"| {e.variant} | " + " | ".join(cells) + " |")
    return lines


def _ranges_text(metrics: dict) -> str:
    parts = []
    for name in ("easy", "hard"):
        intervals = metrics["psi_ranges"].get(name)
        if intervals:
            parts.append(f"{name} " + " ∪ ".join(f"[{lo:g}, {hi:g}]" for lo, hi in intervals))
    return "; ".join(parts)


def _runs_text(metrics: dict) -> str:
    overall = metrics["ranges"].get("overall", next(iter(metrics["ranges"].values())))
    episodes = overall.get("episodes", {})
    if "total" in episodes and "runs" in episodes:
        return f"{episodes['total']} episodes over {episodes['runs']} runs"
    return ""


def _link(root: Path, target: Path, page_dir: Path) -> str:
    """A markdown link target from the page's folder (posix, relative)."""
    return Path(os.path.relpath(target, page_dir)).as_posix()


def task_section(root: Path, page: Path, img_dir: Path, task: str, entries: list[Evaluated], origin: str,
                 seeds: dict | None = None) -> list[str]:
    """Markdown for one task, writing its images under img_dir/<task>/."""
    first = entries[0].metrics
    out = [f"## {task}", ""]
    facts = [f"ψ ranges: {_ranges_text(first)}"]
    if isinstance(first.get("psi_raw"), (int, float)) and math.isfinite(first["psi_raw"]):
        facts.append(f"the clip's own ψ {first['psi_raw']:.2f}")
    if _runs_text(first):
        facts.append(_runs_text(first))
    if first.get("policy_stage") is not None:
        facts.append(f"stage-{first['policy_stage']} policy")
    sources = ", ".join(f"[`{(e.folder / 'metrics.json').relative_to(root).as_posix()}`]"
                        f"({_link(root, e.folder / 'metrics.json', page.parent)})" for e in entries)
    out += [f"{origin}. " + "; ".join(facts) + f". From {sources}.", ""]
    out += _table(entries)
    out += ["", "Succ. in %, E_l-bpe and E_g-bpe in mm, E_smth in rad/s², mean ± std over runs, in the layout of "
            f"*{PAPER_TITLE}*'s table; the report stage prints the paper's own rows beside ours, with its claims "
            "checked, in `reports/<task>/table.md` (from `../shared/paper/figures.yaml` where it is beside the "
            "repository).", ""]
    if seeds is not None:  # the report stage's spread over training seeds (extra_seeds)
        source = root / "reports" / task / "seeds.json"
        out += [seeds_table(seeds, heading="###").strip(), "",
                f"From [`{source.relative_to(root).as_posix()}`]({_link(root, source, page.parent)}).", ""]
    chain = rest_to_rest_table({e.variant: e.metrics for e in entries},
                               {e.variant: json.loads((e.folder / "metrics_dr.json").read_text()) for e in entries
                                if (e.folder / "metrics_dr.json").is_file()})
    if chain:
        out += [chain.strip().replace("## From rest to rest", "### From rest to rest"), ""]
    for e in entries:
        if e.metrics.get("endings"):
            out += [f"{e.variant}. {endings_line(e.metrics['endings'])}", ""]
        if e.metrics.get("stopped_by_time_limit"):
            out += [f"{e.variant}: training was stopped by its wall-clock cap (`stopped_by_time_limit`).", ""]

    task_img = img_dir / task
    plot = task_img / "success_vs_psi.png"
    if plot_success_vs_psi(entries, plot):
        out += [f"![success against ψ, {task}]({_link(root, plot, page.parent)})", ""]
    else:
        out += ["No `per_psi.csv` beside the metrics, so no success-vs-ψ plot.", ""]

    keyframes = task_img / "keyframes.png"
    # A committed policy carries its own figure; a pipeline task's is the keyframes stage's output.
    source = next((e.folder / "keyframes.png" for e in entries if (e.folder / "keyframes.png").is_file()),
                  root / "data" / "keyframes" / task / "keyframes.png")
    if copy_keyframes_figure(source, keyframes) or keyframes.is_file():
        out += [f"Keyframes and their edits (`{source.relative_to(root).as_posix()}`):", "",
                f"![keyframes, {task}]({_link(root, keyframes, page.parent)})", ""]
    else:
        out += [f"No keyframe figure: `{source.relative_to(root).as_posix()}` is made by `dvc repro`.", ""]

    for e in entries:
        gif = task_img / f"rollout_{e.variant}.gif"
        video = rollout_video(e.folder / "media")
        if video is not None:
            video_to_gif(video, gif)
            origin_text = f"`{video.relative_to(root).as_posix()}`"
        elif gif.is_file():
            origin_text = f"a rollout video of `{(e.folder / 'media').relative_to(root).as_posix()}/`"
        else:
            out += [f"{e.variant}: no rollout video in `{(e.folder / 'media').relative_to(root).as_posix()}/` "
                    "(the evaluate stage writes them; run `dvc repro`).", ""]
            continue
        out += [f"{e.variant}, one rollout ({origin_text}):", "",
                f"![rollout, {task}, {e.variant}]({_link(root, gif, page.parent)})", ""]
    return out


def render_page(root: Path, page: Path, img_dir: Path, found: Found) -> str:
    results, pretrained, recipes = found.results, found.pretrained, found.recipes
    out = ["# Results", "",
           "Every evaluated policy in this repository: per task, the table in the paper's layout, success "
           "against ψ, the keyframes and one rollout. Generated by "
           "`.venv/bin/python -m pipeline.evaluation.results_page` from `results/` and `models/pretrained/`; "
           "do not edit by hand. How each figure came about, and what else was measured, is in "
           "[`benchmarks/RESULTS.md`](" + _link(root, root / "benchmarks" / "RESULTS.md", page.parent) + ").", ""]
    by_task: dict[str, list[Evaluated]] = {}
    for e in results:
        by_task.setdefault(e.task, []).append(e)
    for task, entries in by_task.items():
        out += task_section(root, page, img_dir, task, entries, "Trained by `dvc repro` (`params.yaml`)",
                            found.seeds.get(task))
    pre_by_task: dict[str, list[Evaluated]] = {}
    for e in pretrained:
        pre_by_task.setdefault(e.task, []).append(e)
    for task, entries in pre_by_task.items():
        out += task_section(root, page, img_dir, f"{task} (pretrained)" if task in by_task else task, entries,
                            "A committed policy under `models/pretrained/`")
    in_use = chain_balance(root)
    for folder, doc in found.balance:
        out += balance_section(root, page, folder, doc, in_use is None or folder.resolve() == in_use)
    if not by_task and not pre_by_task:
        out += ["No evaluated policy yet: `dvc repro` writes `results/<task>/<variant>/metrics.json`.", ""]
    if recipes:
        out += ["## Recipes without a policy yet", ""]
        for recipe in recipes:
            readme = recipe.folder / "README.md"
            target = readme if readme.is_file() else recipe.folder
            out.append(f"- `{recipe.name}`: [`{target.relative_to(root).as_posix()}`]"
                       f"({_link(root, target, page.parent)}) holds its recipe; no measured policy is committed.")
        out.append("")
    return "\n".join(out).rstrip("\n") + "\n"


def write_results_page(root: str | Path = ".", out: str | Path = "docs/results.md",
                       img_dir: str | Path = "docs/img/results") -> Path:
    """Reads everything first (bad input stops here with nothing written), then writes each image and the
    page atomically."""
    root = Path(root).resolve()
    page = (root / out).resolve()
    images = (root / img_dir).resolve()
    text = render_page(root, page, images, find_results(root))  # every input is read before the first write
    write_text_atomic(page, text)
    return page


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m pipeline.evaluation.results_page",
                                     description="Write docs/results.md from results/ and models/pretrained/.")
    parser.add_argument("--root", type=Path, default=Path("."), help="repository root (default: .)")
    parser.add_argument("--out", type=Path, default=Path("docs/results.md"), help="the page, relative to --root")
    parser.add_argument("--img-dir", type=Path, default=Path("docs/img/results"),
                        help="where its images go, relative to --root")
    args = parser.parse_args(argv)
    try:
        print(f"wrote {write_results_page(args.root, args.out, args.img_dir)}")
    except PipelineInputError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
