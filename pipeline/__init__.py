"""AdaMimic pipeline: human motion in, deployable Unitree G1 policy out."""

import os
from pathlib import Path

# Headless by default (stages render previews and videos); MuJoCo reads this when first imported.
os.environ.setdefault("MUJOCO_GL", "egl")

REPO_ROOT = Path(__file__).resolve().parent.parent
