"""What a catcher's critic says of a chain's handoffs, against what the catcher then does.

    .venv/bin/python benchmarks/handoff_catch.py [models/pretrained/far_jump_rest/export] \
        [--catcher models/pretrained/balance_far_jump/train/policy] [--chains 12]

Runs the export's chain (stand, go, task, balance; `ChainRunner`, nominal model) at `--chains` ψ evenly over
the task's easy range, reads the robot's state on the last task step (the handoff), and prints per ψ the
catch estimate a task paid with `env.rewards.weights.handoff_catch` would get there
(`pipeline/envs/handoff_catch.py`), how the chain ended, and the state's speed, pelvis height and tilt; then the
mean estimate and how well it ranks the chains that stood above those that fell (AUC, when both happened).
The estimate is the catcher's own: `--catcher` a balance training checkpoint (default: the far jump's catcher,
`balance_far_jump`, whose export the default export's chain hands over to).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.envs.handoff_catch import HandoffCatch  # noqa: E402
from pipeline.envs.torch_math import projected_gravity  # noqa: E402
from pipeline.export.chain import ChainRunner, end_ground  # noqa: E402
from pipeline.robot.g1 import load_robot_config  # noqa: E402

DEFAULT_CATCHER = "models/pretrained/balance_far_jump/train/policy"


def handoff_catches(export: Path, catcher: Path, chains: int) -> list[dict]:
    runner = ChainRunner(export)
    estimate = HandoffCatch(catcher, torch.tensor(load_robot_config().default_joint_pos, dtype=torch.float32))
    low, high = runner.task.meta["psi_ranges"]["easy"][0]
    rows = []
    for psi in np.linspace(low, high, chains):
        last = {}

        def keep(model, data, info):
            if info["stretch"] == "task":
                last.update(qpos=data.qpos.copy(), qvel=data.qvel.copy(), ground=end_ground(model, info["keyframe_targets"]))

        result = runner.run(float(psi), on_step=keep)
        if not last or result.ended_in != "balance":  # fell in the task: nothing was handed over
            rows.append({"psi": round(float(psi), 3), "end": result.end, "handed_over": False})
            continue
        qpos = torch.tensor(last["qpos"], dtype=torch.float32)[None]
        qvel = torch.tensor(last["qvel"], dtype=torch.float32)[None]
        catch = float(estimate(qpos, qvel, torch.tensor([last["ground"]], dtype=torch.float32)))
        rows.append({"psi": round(float(psi), 3), "end": result.end, "handed_over": True, "catch": round(catch, 3),
                     "stood": bool(result.standing), "speed_m_s": round(float(np.linalg.norm(last["qvel"][:2])), 2),
                     "pelvis_m": round(float(last["qpos"][2] - last["ground"]), 2),
                     "tilt": round(float(projected_gravity(qpos[:, 3:7])[0, :2].norm()), 2)})
    return rows


def ranking(rows: list[dict]) -> float | None:
    """P(a chain that stood has a higher estimate than one that fell), or None without both."""
    stood = np.array([r["catch"] for r in rows if r.get("stood")])
    fell = np.array([r["catch"] for r in rows if r["handed_over"] and not r["stood"]])
    if not len(stood) or not len(fell):
        return None
    return float((stood[:, None] > fell[None, :]).mean() + 0.5 * (stood[:, None] == fell[None, :]).mean())


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("export", type=Path, nargs="?", default=Path("models/pretrained/far_jump_rest/export"))
    parser.add_argument("--catcher", type=Path, default=Path(DEFAULT_CATCHER))
    parser.add_argument("--chains", type=int, default=12)
    args = parser.parse_args(argv)
    rows = handoff_catches(args.export, args.catcher, args.chains)
    for row in rows:
        print(json.dumps(row))
    handed = [r["catch"] for r in rows if r["handed_over"]]
    print(json.dumps({"export": str(args.export), "catcher": str(args.catcher), "handed_over": len(handed),
                      "stood": sum(bool(r.get("stood")) for r in rows),
                      "mean_catch": round(float(np.mean(handed)), 3) if handed else None, "auc": ranking(rows)}))


if __name__ == "__main__":
    main()
