"""The committed balance policy's standing rate under the paper's domain randomisation and pushes.

    .venv/bin/python benchmarks/balance_standing.py [--episodes 1000] [--seconds 10] [--starts stance|recorded]

Runs `pipeline.balance.evaluate.standing_rate` (the balance env, its pushes up to 0.5 m/s every 1-3 s, the
paper's randomisation, deterministic actions) on the trained policy of params.yaml `balance.out` (the one the
chains use, models/pretrained/balance_landing) and prints one line, e.g.
`starts=stance episodes=1000 seconds=10 upright=96.3 standing=48.6 fell=3.2` (%; the goal: upright >= 99).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.balance.evaluate import standing_rate  # noqa: E402
from pipeline.config import load_params  # noqa: E402
from pipeline.rl.checkpoint import load_policy  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--starts", choices=("stance", "recorded"), default="stance")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    params = load_params("params.yaml")
    cfg, root = params.balance, params.path.parent
    policy, _ = load_policy(root / cfg.out / "train" / "policy")
    r = standing_rate(policy, cfg, root=root, starts=args.starts, episodes=args.episodes, seconds=args.seconds,
                      seed=args.seed)
    print(f"starts={r['starts']} episodes={r['episodes']} seconds={r['seconds']:g} upright={r['upright']:.1f} "
          f"standing={r['standing']:.1f} fell={r['fell']:.1f}")


if __name__ == "__main__":
    main()
