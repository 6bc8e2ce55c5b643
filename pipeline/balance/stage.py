"""`stages/train_balance.py`: train the balance policy, export it and measure how it stands.

Not a `dvc repro` stage: the policy is committed under `balance.out` (models/pretrained/balance_landing) and
every task's chain reads it from there, so a fresh clone never retrains it. Rerun it after changing
`balance:` in params.yaml (chunked: `--chunk-minutes M`, then `--resume`).
"""

from __future__ import annotations

import json

from pipeline.common.atomic import write_text_atomic


def run_train_balance(params, args) -> None:
    """Train (or resume) the balance policy, export it, and write its standing rates to metrics.json."""
    from pipeline.balance.evaluate import standing_rate
    from pipeline.balance.export import export_balance
    from pipeline.balance.train import train_balance
    from pipeline.rl.checkpoint import load_policy
    from pipeline.stages import _chunk_s, _finish_training

    cfg, root = params.balance, params.path.parent
    out = root / cfg.out
    training = train_balance(cfg, out / "train", root=root, resume=args.resume, chunk_s=_chunk_s(args))
    if training.get("paused"):
        _finish_training(training)
    result = export_balance(cfg, out / "train" / "policy", out / "export")
    policy, _ = load_policy(out / "train" / "policy")
    metrics = {"training": training, "parity_max_abs_diff": result.parity_max_abs_diff,
               "stance": standing_rate(policy, cfg, root=root, starts="stance")}
    if cfg.start_states_path(root) is not None and cfg.start_states_path(root).is_file():
        metrics["recorded"] = standing_rate(policy, cfg, root=root, starts="recorded")
    write_text_atomic(out / "metrics.json", json.dumps(metrics, indent=1, default=float))
    print(json.dumps(metrics, indent=1, default=float))
