"""The results page's section on the balance policy (models/pretrained/<name>/ whose export is `kind: balance`):
its standing rates from the metrics.json that stages/train_balance.py writes."""

from __future__ import annotations

import json
import os
from pathlib import Path

from pipeline.common.errors import PipelineInputError


def _link(target: Path, page_dir: Path) -> str:
    return Path(os.path.relpath(target, page_dir)).as_posix()


def is_balance_policy(folder: Path) -> bool:
    meta = folder / "export" / "policy.json"
    return meta.is_file() and json.loads(meta.read_text()).get("kind") == "balance"


def read_balance_metrics(path: Path) -> dict:
    """metrics.json of stages/train_balance.py, checked for the standing rates the page shows."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise PipelineInputError(path, None, f"cannot be read as JSON ({error})") from None
    for starts in ("stance", "recorded"):
        if starts in doc:
            for key in ("upright", "standing", "fell", "episodes", "seconds"):
                if not isinstance(doc[starts].get(key), (int, float)):
                    raise PipelineInputError(path, f"{starts}.{key}", "missing or not a number")
    if "stance" not in doc:
        raise PipelineInputError(path, "stance", "missing: the standing rate from the stance")
    return doc


def balance_section(root: Path, page: Path, folder: Path, doc: dict, in_use: bool = True) -> list[str]:
    """The standing rates of one committed balance policy; `in_use`: the one the chains hand over to
    (params.yaml `balance.out`)."""
    source = folder / "metrics.json"
    role = ("Every chain the pipeline exports stands with it before the go and after the task" if in_use else
            "A committed balance policy the pipeline's exports do not hand over to (params.yaml `balance.out` names "
            "the one they do; a committed task policy's own export may name this one)")
    out = [f"## The balance policy `{folder.name}`", "",
           f"{role} (`models/pretrained/{folder.name}`). "
           f"From [`{source.relative_to(root).as_posix()}`]({_link(source, page.parent)}).", "",
           "| starts | episodes | seconds | upright (%) | standing (%) | fell (%) |", "|---|---|---|---|---|---|"]
    for starts, label in (("stance", "the stance at rest"), ("recorded", "the task policies' recorded states")):
        if starts in doc:
            r = doc[starts]
            out.append(f"| {label} | {r['episodes']} | {r['seconds']:g} | {r['upright']:.1f} | {r['standing']:.1f} | "
                       f"{r['fell']:.1f} |")
    out += ["", "Under the paper's domain randomisation and pushes (base velocity kicks up to 0.5 m/s every 1–3 s). "
            "Upright: no fall and |g_xy| < 0.3 at the end; standing: also pelvis ≥ 0.55 m and base speed < 0.2 m/s "
            "then (a push may have just landed).", ""]
    return out
