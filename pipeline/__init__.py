"""AdaMimic pipeline: human motion in, deployable Unitree G1 policy out."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
