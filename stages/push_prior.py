"""DVC stage `push_prior`: see pipeline.stages.run_push_prior."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pipeline.cli import stage_main  # noqa: E402
from pipeline.stages import run_push_prior  # noqa: E402

if __name__ == "__main__":
    stage_main(run_push_prior)
