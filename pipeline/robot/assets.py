"""Fetches the G1 MJCF and meshes from the mjlab wheel on PyPI (BSD-3) at set-up time.

Only `pip download --no-deps` is used: mjlab itself is never installed (it pins another mujoco).
Run `python -m pipeline.robot.assets` once; `make` targets do it for you.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from pipeline import REPO_ROOT
from pipeline.common.atomic import atomic_dir

ROBOT_DIR = REPO_ROOT / "robots" / "g1"
VENDOR_DIR = ROBOT_DIR / "vendor"
WHEEL_REQUIREMENT = "mjlab==1.6.0"
DIR_IN_WHEEL = "mjlab/asset_zoo/robots/unitree_g1/xmls/"


class MissingRobotAssets(FileNotFoundError):
    pass


def mjcf_path() -> Path:
    path = VENDOR_DIR / "xmls" / "g1.xml"
    if not path.exists():
        raise MissingRobotAssets(
            f"{path} is missing: fetch the G1 model once with `python -m pipeline.robot.assets` "
            "(or `make setup`)."
        )
    return path


def fetch(force: bool = False) -> Path:
    if (VENDOR_DIR / "xmls" / "g1.xml").exists() and not force:
        return VENDOR_DIR
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(
            [sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", "-d", tmp, WHEEL_REQUIREMENT],
            check=True,
        )
        wheel = next(Path(tmp).glob("mjlab-*.whl"))
        with atomic_dir(VENDOR_DIR) as staging, zipfile.ZipFile(wheel) as archive:
            for name in archive.namelist():
                if name.startswith(DIR_IN_WHEEL) and not name.endswith("/"):
                    target = staging / "xmls" / name[len(DIR_IN_WHEEL):]
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_bytes(archive.read(name))
            (staging / "SOURCE").write_text(
                f"Extracted from {wheel.name} ({DIR_IN_WHEEL}); licence BSD-3-Clause (mjlab).\n"
            )
    return VENDOR_DIR


if __name__ == "__main__":
    print(f"G1 assets in {fetch(force='--force' in sys.argv)}")
