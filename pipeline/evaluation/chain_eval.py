"""`rest_to_rest`: the evaluation of a task's whole chain (stand → go → task → balance), per ψ range.

Runs `export.chain.ChainRunner` (the loop `adamimic sim2sim` and `rehearse` judge with) at ψ values
spread evenly inside each range, from the stance at rest. Under domain randomisation each episode
draws the paper's table (`envs.config.RandomizationConfig`, as training does: masses, centre of mass,
friction, restitution, gains, motor strength, control delay) into its own model.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import RandomizationConfig
from pipeline.envs.randomization import DomainRandomizer
from pipeline.evaluation.evaluate import spread_in_ranges
from pipeline.export.chain import ChainRunner

RATES = ("rest_to_rest", "success", "standing")


class _OneModel:
    """A single MjModel behind the backend method the randomiser writes through."""

    def __init__(self, model):
        self.model = model

    def set_model_field(self, name: str, world_ids, values) -> None:
        getattr(self.model, name)[:] = np.asarray(values)[0]


def model_randomizer(cfg: RandomizationConfig):
    """randomize(model) -> control delay (s): one draw of `cfg`'s table, switched on whatever its `enabled`
    says, into `model` (torch's RNG seeds it)."""
    cfg = copy.deepcopy(cfg)
    cfg.enabled = True

    def randomize(model) -> float:
        return float(DomainRandomizer(cfg, model, _OneModel(model)).apply(np.array([0]))[0])

    return randomize


def evaluate_chain(export_dir: str | Path, psi_ranges: dict, episodes_per_range: int, *,
                   randomization: RandomizationConfig | None = None, seed: int = 0) -> dict:
    """{"ranges": {name: {rate: {"mean": %}, "episodes": n}}, "endings": {...}, "episodes": [...]}; the
    overall range pools every episode."""
    runner = ChainRunner(export_dir)
    randomize = model_randomizer(randomization) if randomization is not None else None
    torch.manual_seed(seed)
    episodes = []
    for name, psi in spread_in_ranges(psi_ranges, list(psi_ranges), episodes_per_range):
        result = runner.run(psi, randomize=randomize).to_json()
        episodes.append(dict(result, range=name))
    ranges = {}
    for name in [*psi_ranges, "overall"]:
        chosen = [e for e in episodes if name == "overall" or e["range"] == name]
        ranges[name] = {rate: {"mean": 100.0 * float(np.mean([e[rate] for e in chosen]))} for rate in RATES}
        ranges[name]["episodes"] = len(chosen)
    endings: dict[str, int] = {}
    for e in episodes:
        key = f"{e['ended_in']}:{e['end']}"
        endings[key] = endings.get(key, 0) + 1
    return {"chain": runner.chain, "domain_randomization": randomization is not None, "seed": seed,
            "ranges": ranges, "endings": dict(sorted(endings.items())), "episodes": episodes}


def merge_chain(doc: dict, nominal: dict) -> None:
    """Adds a nominal chain evaluation to a metrics.json document: `rest_to_rest`, `standing` and the chain's own
    task-stretch `chain_success` beside the paper's success in each range, and where the chains ended."""
    for name, rates in nominal["ranges"].items():
        doc["ranges"].setdefault(name, {}).update(rest_to_rest=rates["rest_to_rest"], standing=rates["standing"],
                                                  chain_success=rates["success"])
    doc["chain"] = {k: nominal[k] for k in ("chain", "endings")}


def read_policy_folder(folder: str | Path) -> tuple[dict, dict]:
    """(export/policy.json, metrics.json) of a committed policy folder; a missing one is refused, naming it."""
    folder = Path(folder)
    docs = []
    for needed in (folder / "export" / "policy.json", folder / "metrics.json"):
        if not needed.is_file():
            raise PipelineInputError(needed, None, "missing: a committed policy folder holds export/ and the evaluate "
                                     "stage's metrics.json")
        docs.append(json.loads(needed.read_text()))
    return docs[0], docs[1]


def add_chain_metrics(folder: str | Path, episodes_per_range: int = 32, seed: int = 0) -> dict:
    """A committed policy folder (export/ with its chain, the evaluate stage's metrics.json) judged as a chain:
    `rest_to_rest`, `standing` and `chain_success` added to each range of metrics.json, metrics_dr.json written
    (the same as the evaluate stage does for a policy it trains). Returns the nominal chain evaluation."""
    from pipeline.common.atomic import write_text_atomic
    from pipeline.evaluation.run import chain_document

    meta, doc = read_policy_folder(folder)
    folder = Path(folder)
    psi_ranges = {name: meta["psi_ranges"][name] for name in ("easy", "hard") if name in meta["psi_ranges"]}
    nominal = evaluate_chain(folder / "export", psi_ranges, episodes_per_range, seed=seed)
    randomised = evaluate_chain(folder / "export", psi_ranges, episodes_per_range, randomization=RandomizationConfig(),
                                seed=seed)
    merge_chain(doc, nominal)
    write_text_atomic(folder / "metrics.json", json.dumps(doc, indent=2, allow_nan=True))
    write_text_atomic(folder / "metrics_dr.json", json.dumps(chain_document(meta["task"], meta.get("variant", "adamimic"),
                                                                          randomised), indent=2, allow_nan=True))
    return nominal


def main(argv=None) -> int:
    import argparse
    import sys

    parser = argparse.ArgumentParser(prog="python -m pipeline.evaluation.chain_eval",
                                     description="Judge committed policy folders as chains: add rest_to_rest to their "
                                                 "metrics.json and write metrics_dr.json.")
    parser.add_argument("folders", nargs="+", type=Path, help="models/pretrained/<task> (export/ with its chain, metrics.json)")
    parser.add_argument("--episodes", type=int, default=32, help="chains per ψ range (default 32)")
    args = parser.parse_args(argv)
    try:
        for folder in args.folders:  # every folder checked before any is written
            read_policy_folder(folder)
        for folder in args.folders:
            result = add_chain_metrics(folder, episodes_per_range=args.episodes)
            print(folder, {name: r["rest_to_rest"]["mean"] for name, r in result["ranges"].items()}, result["endings"])
    except PipelineInputError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
