"""`adamimic share` writes hub-format folders (tested offline: no push without --repo-id)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from pipeline import REPO_ROOT
from pipeline.common.errors import PipelineInputError
from pipeline.motion import RobotKinematics
from pipeline.motion.dataset import read_motions, write_motions
from pipeline.share import share


@pytest.fixture(scope="module")
def motion():
    kin = RobotKinematics()
    t = 20
    root = np.tile([0.0, 0.0, 0.76], (t, 1)) + np.linspace(0, 0.2, t)[:, None] * [1, 0, 0]
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (t, 1))
    joints = np.tile(kin.config.default_joint_pos, (t, 1))
    return kin.motion(50.0, root, quat, joints, name="walk")


def _front_matter(readme: str) -> dict:
    assert readme.startswith("---\n")
    return yaml.safe_load(readme.split("---\n")[1])


def test_share_dataset_folder(tmp_path, motion):
    write_motions(tmp_path / "ds", [motion])
    message = share(tmp_path / "ds", tmp_path / "hub")
    assert "dataset" in message and "--repo-id" in message
    meta = _front_matter((tmp_path / "hub" / "README.md").read_text())
    assert "LeRobot" in meta["tags"] and meta["task_categories"] == ["robotics"]
    (shared,) = read_motions(tmp_path / "hub")  # still a readable dataset
    np.testing.assert_array_equal(shared.joint_pos, motion.joint_pos)


def test_share_policy_folder_via_cli(tmp_path):
    policy = tmp_path / "policy"
    policy.mkdir()
    (policy / "config.json").write_text(json.dumps({"task": "far_jump", "variant": "adamimic"}))
    (policy / "model.safetensors").write_bytes(b"weights")
    (policy / "training_state.pt").write_bytes(b"optimizer")
    result = subprocess.run([sys.executable, "-m", "pipeline.cli", "share", str(policy), "--out", str(tmp_path / "hub")],
                            cwd=REPO_ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    hub = tmp_path / "hub"
    assert (hub / "model.safetensors").read_bytes() == b"weights"
    assert not (hub / "training_state.pt").exists()  # training state stays private
    assert "far_jump" in (hub / "README.md").read_text()


def test_share_refuses_unknown_folder(tmp_path):
    (tmp_path / "junk").mkdir()
    with pytest.raises(PipelineInputError, match="neither a LeRobot dataset"):
        share(tmp_path / "junk", tmp_path / "hub")
    assert not (tmp_path / "hub").exists()
    result = subprocess.run([sys.executable, "-m", "pipeline.cli", "share", str(tmp_path / "junk"), "--out",
                             str(tmp_path / "hub")], cwd=REPO_ROOT, capture_output=True, text=True)
    assert result.returncode == 2 and "neither" in result.stderr
