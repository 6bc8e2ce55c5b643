"""DVC stage `train_stage2`: see pipeline.stages.run_train_stage2."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.cli import stage_main  # noqa: E402
from pipeline.stages import run_train_stage2  # noqa: E402

if __name__ == "__main__":
    stage_main(run_train_stage2)
