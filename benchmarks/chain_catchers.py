"""Which balance policy catches a task's chain best: one committed task policy, its chain's balance policy swapped.

    .venv/bin/python benchmarks/chain_catchers.py models/pretrained/jump_step_down_rest \
        models/pretrained/balance_heading models/pretrained/balance_heading_long [--episodes 16]

For each balance policy folder (its `export/`): a copy of the task's export with `balance/` replaced, the
heading the balance policy leaves the robot in at the go (2 s on it from yaw 0, the easy range's middle ψ,
nominal model), and `rest_to_rest` (%) per range over `--episodes` chains a range, nominal and under the
paper's randomisation (`pipeline.evaluation.chain_eval.evaluate_chain`). One line per balance policy, e.g.
`balance_heading yaw_at_go=-13.8 nominal easy=87.5 hard=62.5 randomised easy=18.8 hard=6.2 endings=...`.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.envs.config import RandomizationConfig  # noqa: E402
from pipeline.evaluation.chain_eval import evaluate_chain  # noqa: E402
from pipeline.export.chain import ChainRunner, read_chain  # noqa: E402
from pipeline.export.policy_step import yaw_of  # noqa: E402
from pipeline.export.sim2sim import PsiOutOfRangeWarning  # noqa: E402


def with_catcher(task_export: Path, balance_folder: Path, scratch: Path) -> Path:
    """A copy of `task_export` whose chain hands over to `balance_folder`'s export."""
    export = scratch / balance_folder.name
    shutil.copytree(task_export, export)
    inside = export / read_chain(export)["balance"]
    shutil.rmtree(inside)
    shutil.copytree(balance_folder / "export", inside)
    return export


def yaw_at_go(export: Path, psi: float) -> float:
    """Degrees the base has turned from the stance's yaw 0 when the task policy takes over."""
    seen = []

    def on_step(model, data, info):
        if info["stretch"] == "task" and not seen:
            seen.append(float(np.degrees(yaw_of(data.qpos[3:7]))))

    ChainRunner(export).run(psi, on_step=on_step)
    return seen[0] if seen else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("task", type=Path, help="a committed task policy folder (its export/ has a chain)")
    parser.add_argument("balance", type=Path, nargs="+", help="balance policy folders (each with export/)")
    parser.add_argument("--episodes", type=int, default=16, help="chains a range")
    args = parser.parse_args()
    warnings.simplefilter("ignore", PsiOutOfRangeWarning)
    meta = json.loads((args.task / "export" / "policy.json").read_text())
    ranges = {name: meta["psi_ranges"][name] for name in ("easy", "hard") if name in meta["psi_ranges"]}
    middle = float(np.mean(ranges["easy"][0]))
    with tempfile.TemporaryDirectory(prefix="chain-catchers-") as scratch:
        for folder in args.balance:
            export = with_catcher(args.task / "export", folder, Path(scratch))
            line = [folder.name, f"yaw_at_go={yaw_at_go(export, middle):.1f}"]
            for label, randomization in (("nominal", None), ("randomised", RandomizationConfig())):
                result = evaluate_chain(export, ranges, args.episodes, randomization=randomization)
                line.append(label + " " + " ".join(f"{name}={result['ranges'][name]['rest_to_rest']['mean']:.1f}"
                                                   for name in ranges))
                if randomization is not None:
                    line.append("endings=" + ",".join(f"{k}:{v}" for k, v in result["endings"].items()))
            print(" ".join(line), flush=True)


if __name__ == "__main__":
    main()
