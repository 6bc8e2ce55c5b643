"""The paper's own rows beside ours, and its claims checked on our rows.

The published figures (main simulation table: success, E_l-bpe, E_g-bpe, E_smth on the easy, hard and overall
ranges, Isaac Gym, 4096 envs) are read from `figures.yaml` (by default `../shared/paper/figures.yaml` beside this
repository; not copied here). `paper_table` prints, per variant we evaluated, our row and the paper's row;
`claims` says whether each of the paper's comparative claims holds on our rows (and on the paper's own).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from pipeline.common.errors import PipelineInputError
from pipeline.evaluation.metrics import METRIC_NAMES

FIGURES = Path(__file__).resolve().parents[2].parent / "shared" / "paper" / "figures.yaml"
PAPER_SETTING = "Isaac Gym, 4096 envs, > 10 000 episodes per evaluation"
BASELINES = ("amp_style", "amp_mimic", "deepmimic_noadapt", "deepmimic_adapt", "deepmimic_adapt_dphi", "adamimic_dense")


def load_paper_rows(path: str | Path = FIGURES) -> dict[str, dict] | None:
    """{variant: {range: {metric: value}}} of the paper's main table, or None where the file is absent."""
    path = Path(path)
    if not path.is_file():
        return None
    raw = yaml.safe_load(path.read_text()).get("main_simulation")
    if not isinstance(raw, dict) or "rows" not in raw or "columns" not in raw:
        raise PipelineInputError(path, "main_simulation", "needs `columns` and `rows`")
    columns = raw["columns"]
    if sorted(columns) != sorted(METRIC_NAMES):
        raise PipelineInputError(path, "main_simulation.columns", f"expected {list(METRIC_NAMES)}, got {columns}")
    rows = {}
    for variant, ranges in raw["rows"].items():
        rows[variant] = {}
        for name, values in ranges.items():
            if len(values) != len(columns):
                raise PipelineInputError(path, f"main_simulation.rows.{variant}.{name}", f"needs {len(columns)} values")
            rows[variant][name] = dict(zip(columns, map(float, values)))
    return rows


def _ours(docs: dict[str, dict]) -> dict[str, dict]:
    return {v: {g: {m: float(r[m]["mean"]) for m in METRIC_NAMES if m in r} for g, r in d["ranges"].items()}
            for v, d in docs.items()}


def paper_table(docs: dict[str, dict], paper: dict[str, dict]) -> str:
    """Markdown: for each variant we evaluated, our row then the paper's (marked), on easy / hard / overall."""
    groups = ("easy", "hard", "overall")
    short = {"success": "Succ.↑", "e_l_bpe": "E_l-bpe↓", "e_g_bpe": "E_g-bpe↓", "e_smth": "E_smth↓"}
    lines = ["\n## Beside the paper's rows\n",
             f"Ours (this repository's evaluation) and the paper's published row for each variant we evaluated; the "
             f"paper's: {PAPER_SETTING}, over its seven tasks. Succ. in %, E_l-bpe and E_g-bpe in mm, E_smth rad/s².\n",
             "| Method | " + " | ".join(f"{g} {short[m]}" for g in groups for m in METRIC_NAMES) + " |",
             "|---|" + "---|" * (len(groups) * len(METRIC_NAMES))]
    ours = _ours(docs)
    for variant in docs:
        for label, rows in ((variant, ours), (f"{variant} (paper)", paper)):
            row = rows.get(variant, {})
            cells = [f"{row[g][m]:.1f}" if g in row and m in row[g] and np.isfinite(row[g][m]) else "–"
                     for g in groups for m in METRIC_NAMES]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _claim_checks(rows: dict[str, dict]) -> list[tuple[str, bool | None]]:
    def get(variant, metric, group="overall"):
        return rows.get(variant, {}).get(group, {}).get(metric)

    def lower(a, b, metric):
        x, y = get(a, metric), get(b, metric)
        return None if x is None or y is None else x < y

    freeze = None
    if get("adamimic", "success") is not None and get("adamimic_nofreeze", "success") is not None:
        freeze = get("adamimic", "success") > get("adamimic_nofreeze", "success") and lower("adamimic", "adamimic_nofreeze", "e_g_bpe")
    present = [b for b in BASELINES if get(b, "success", "easy") is not None]
    easy = None if get("adamimic", "success", "easy") is None or not present else \
        all(get("adamimic", "success", "easy") >= get(b, "success", "easy") for b in present)
    return [("the adapters lower E_g-bpe against stage 1 alone (adamimic < adamimic_stage1)",
             lower("adamimic", "adamimic_stage1", "e_g_bpe")),
            ("sparse keyframe edits beat rule-based dense tracking on E_g-bpe (adamimic < deepmimic_adapt)",
             lower("adamimic", "deepmimic_adapt", "e_g_bpe")),
            ("freezing stage 1 beats not freezing it (adamimic over adamimic_nofreeze: higher success, lower E_g-bpe)",
             freeze),
            ("AdaMimic's easy success is at least every baseline's" + (f" ({', '.join(present)})" if present else ""),
             easy)]


def claims(docs: dict[str, dict], paper: dict[str, dict] | None) -> str:
    """Markdown list: each claim, whether it holds here (overall range), and in the paper's own rows."""
    word = {True: "holds", False: "does not hold", None: "not measured (a variant is missing)"}
    ours = _claim_checks(_ours(docs))
    theirs = _claim_checks(paper) if paper is not None else [(text, None) for text, _ in ours]
    lines = ["\n### The paper's claims, on our rows\n"]
    for (text, here), (_, there) in zip(ours, theirs):
        lines.append(f"- {text}: here {word[here]}" + (f"; in the paper's rows {word[there]}" if paper is not None else ""))
    return "\n".join(lines) + "\n"


def paper_section(docs: dict[str, dict], path: str | Path = FIGURES) -> str:
    """The report's paper comparison: the rows and the claims, or one line saying where the figures would be."""
    paper = load_paper_rows(path)
    if paper is None:
        return (f"\n## Beside the paper's rows\n\nThe paper's figures file is not at `{path}`: its rows are not "
                "printed here.\n" + claims(docs, None))
    return paper_table(docs, paper) + claims(docs, paper)
