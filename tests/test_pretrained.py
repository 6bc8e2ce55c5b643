"""The policies committed under models/pretrained/: each plays from its export alone and does what its files say.

A committed policy folder holds `export/` (ONNX + metadata, hub format), the evaluate stage's `metrics.json` and
`sim2sim.json`, the output of `adamimic sim2sim <folder>/export --psi ...` when it was committed. Replaying the
same ψ values here, from a copy of `export/` alone (no `../shared`, no `data/`), must end every episode the same
way: the same success, the same ending, the same step, and keyframe errors within a millimetre.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = sorted(p.parent.parent for p in (ROOT / "models" / "pretrained").glob("*/export/policy.onnx"))


@pytest.mark.parametrize("folder", COMMITTED, ids=[p.name for p in COMMITTED])
def test_committed_policy_replays_its_recorded_episodes_from_the_export_alone(folder, tmp_path):
    from pipeline.export.sim2sim import run_sim2sim

    recorded = json.loads((folder / "sim2sim.json").read_text())
    export = shutil.copytree(folder / "export", tmp_path / "export")
    replayed = run_sim2sim(export, psi_values=[e["psi"] for e in recorded["episodes"]])

    assert replayed["task"] == recorded["task"]
    for want, got in zip(recorded["episodes"], replayed["episodes"], strict=True):
        assert (got["success"], got["end"], got["steps"]) == (want["success"], want["end"], want["steps"]), got["psi"]
        assert len(got["keyframe_errors"]) == len(want["keyframe_errors"])
        for a, b in zip(got["keyframe_errors"], want["keyframe_errors"]):
            assert abs(a - b) < 1e-3, (got["psi"], got["keyframe_errors"], want["keyframe_errors"])
    assert math.isclose(replayed["success"], recorded["success"])


@pytest.mark.parametrize("folder", COMMITTED, ids=[p.name for p in COMMITTED])
def test_committed_policy_metrics_belong_to_its_export(folder):
    metrics = json.loads((folder / "metrics.json").read_text())
    policy = json.loads((folder / "export" / "policy.json").read_text())
    assert metrics["task"] == policy["task"]
    assert metrics.get("variant", "adamimic") == policy.get("variant", "adamimic")
    for name in ("easy", "hard"):
        assert 0.0 <= metrics["ranges"][name]["success"]["mean"] <= 100.0
