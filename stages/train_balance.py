"""Train, export and measure the balance policy (params.yaml `balance:`): see pipeline.balance.stage."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.balance.stage import run_train_balance  # noqa: E402
from pipeline.cli import stage_main  # noqa: E402

if __name__ == "__main__":
    stage_main(run_train_balance)
