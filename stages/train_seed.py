"""DVC stage `train_seed`: see pipeline.stages.run_train_seed."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.cli import stage_main  # noqa: E402
from pipeline.stages import run_train_seed  # noqa: E402

if __name__ == "__main__":
    stage_main(run_train_seed)
