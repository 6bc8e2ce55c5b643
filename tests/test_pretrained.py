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
EXPORTS = sorted(p.parent.parent for p in (ROOT / "models" / "pretrained").glob("*/export/policy.onnx"))
BALANCE = [p for p in EXPORTS if json.loads((p / "export" / "policy.json").read_text()).get("kind") == "balance"]
COMMITTED = [p for p in EXPORTS if p not in BALANCE]  # the task policies
CHAINED = [p for p in COMMITTED if (p / "rest_to_rest.json").is_file()]


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


@pytest.mark.parametrize("folder", CHAINED, ids=[p.name for p in CHAINED])
def test_committed_chain_replays_its_recorded_episodes_from_the_export_alone(folder, tmp_path):
    """`rest_to_rest.json`: `adamimic sim2sim <folder>/export --psi ...` (stand, go, task, balance) when it was
    committed; the same verdicts from a copy of `export/` alone."""
    from pipeline.export.chain import ChainRunner

    recorded = json.loads((folder / "rest_to_rest.json").read_text())
    runner = ChainRunner(shutil.copytree(folder / "export", tmp_path / "export"))
    for want in recorded["episodes"]:
        got = runner.run(want["psi"]).to_json()
        for key in ("success", "standing", "rest_to_rest", "end", "ended_in", "steps"):
            assert got[key] == want[key], (want["psi"], key, got[key], want[key])


@pytest.mark.parametrize("folder", BALANCE, ids=[p.name for p in BALANCE])
def test_committed_balance_policy_stands_from_its_export_alone(folder, tmp_path):
    """The balance export in MuJoCo with onnxruntime only (no torch), from the stance at rest on flat ground:
    standing after 5 s, as its metrics.json says it does under pushes and randomisation too."""
    import mujoco
    import numpy as np

    from pipeline.export.chain import judge_standing
    from pipeline.export.policy_step import PolicyStepper
    from pipeline.export.sim2sim import RobotState, build_scene, load_exported
    from pipeline.robot.g1 import default_qpos

    session, meta = load_exported(shutil.copytree(folder / "export", tmp_path / "export"))
    stepper = PolicyStepper(session, meta)
    model = build_scene(meta, 0.0)  # flat ground, the export's gains and physics
    data = mujoco.MjData(model)
    data.qpos[:] = default_qpos()
    mujoco.mj_forward(model, data)
    joints = [model.joint(n).id for n in meta["joint_names"]]
    state = RobotState(model, data, model.jnt_qposadr[joints], model.jnt_dofadr[joints])
    actuators = [model.actuator(n).id for n in meta["joint_names"]]
    for _ in range(250):
        out = stepper.step(base_ang_vel=state.base_ang_vel(), projected_gravity=state.projected_gravity(),
                           joint_pos=state.joint_pos(), joint_vel=state.joint_vel(), psi=0.0)
        data.ctrl[actuators] = out.joint_targets
        for _ in range(int(round(meta["control_dt"] / model.opt.timestep))):
            mujoco.mj_step(model, data)
    assert judge_standing(model, data.qpos, float(np.linalg.norm(data.qvel[0:3]))), data.qpos[:7]
    metrics = json.loads((folder / "metrics.json").read_text())
    assert 0.0 <= metrics["stance"]["upright"] <= 100.0 and metrics["stance"]["episodes"] >= 1000
