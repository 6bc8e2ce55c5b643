"""The chain an export holds (stand → go → task → balance), its judge, and its refusals."""

import json
import shutil

import mujoco
import numpy as np
import pytest
import torch
from torch import nn

from pipeline.common.errors import PipelineInputError
from pipeline.export.chain import CHAIN_NAME, ChainRunner, judge_standing, read_chain, stance_state, write_chain


class StillNet(nn.Module):
    """A stand-in balance network: a zero action, whatever it observes."""

    def forward(self, obs):
        return torch.zeros(obs.shape[0], 27) + 0.0 * obs[:, :1]


def standin_balance_export(folder):
    """A balance export with the real metadata contract and a network that never moves (tests only)."""
    from pipeline.balance.config import BalanceConfig
    from pipeline.balance.export import balance_metadata
    from pipeline.envs.balance_env import balance_actuation
    from pipeline.export.onnx_export import DeployedPolicy, export_folder
    from pipeline.robot.g1 import load_robot_config

    robot, cfg = load_robot_config(), BalanceConfig()
    meta = balance_metadata(cfg, robot)
    target, scale = balance_actuation(cfg.env, robot)
    meta["action_scale"], meta["stance"]["joint_target"] = scale.tolist(), target.tolist()
    module = DeployedPolicy(StillNet(), target, scale)
    return export_folder(module, meta["observation"]["dim"], meta, folder).folder


def chained_export(task_export, folder, balance=None, **chain):
    """A copy of `task_export` with a balance export and chain.json."""
    shutil.copytree(task_export, folder)
    balance = balance or standin_balance_export(folder.parent / f"{folder.name}_balance")
    write_chain(folder, balance, **chain)
    return folder


def _standin_task():
    """(deployed module, observation dim, metadata) of a far-jump export with a stand-in network and the real
    metadata contract, as tests/test_export.py makes them."""
    from test_export import ComposedStandIn, _tracking_data

    from pipeline.export.metadata import build_metadata, observation_layout
    from pipeline.export.onnx_export import DeployedPolicy
    from pipeline.robot.g1 import load_robot_config

    torch.manual_seed(0)
    cfg = load_robot_config()
    layout = observation_layout(cfg, history=5)
    module = DeployedPolicy(ComposedStandIn(layout["dim"]), cfg.default_joint_pos, cfg.action_scale)
    return module, layout["dim"], build_metadata(task="far_jump", variant="adamimic", robot=cfg, data=_tracking_data(),
                                                 obs_layout=layout)


def standin_task_export(folder):
    from pipeline.export.onnx_export import export_folder

    return export_folder(*_standin_task(), folder).folder


@pytest.fixture(scope="module")
def chain_export(tmp_path_factory):
    root = tmp_path_factory.mktemp("chain")
    return chained_export(standin_task_export(root / "task"), root / "export", stand_s=0.4, after_s=0.4)


def test_the_chain_starts_standing_at_rest_and_runs_stand_task_balance(chain_export):
    runner = ChainRunner(chain_export)
    seen = []

    def on_step(model, data, info):
        if not seen:
            seen.append(("first", data.qpos.copy(), data.qvel.copy()))
        seen.append((info["stretch"], info["phase"]))

    result = runner.run(1.4, on_step=on_step)
    stretches = [s for s, _ in seen[1:]]
    assert stretches[:20] == ["stand"] * 20 and stretches.count("stand") == result.steps["stand"] == 20
    assert stretches[20] == "task" and result.steps["task"] == stretches.count("task")
    # the robot starts in the default pose at the task's start, not in the policy's trained state
    meta = json.loads((chain_export / "policy.json").read_text())
    first_qpos = seen[0][1]
    assert np.allclose(first_qpos[7:], meta["default_joint_pos"], atol=0.05)
    assert np.allclose(first_qpos[:2], meta["initial_state"]["qpos"][:2], atol=0.05)
    if result.ended_in == "balance":  # handed over: phase 1 reached, then the balance policy
        assert seen[20 + result.steps["task"]][1] >= 1.0 - 1e-6
        assert stretches[-1] == "balance"
    assert result.rest_to_rest == (result.success and result.standing)
    assert set(result.to_json()) >= {"psi", "success", "standing", "rest_to_rest", "keyframe_errors", "end"}


def test_judge_standing_reads_tilt_height_speed_and_ground():
    from pipeline.robot.g1 import build_model, default_qpos

    model = build_model()
    qpos = default_qpos()
    assert judge_standing(model, qpos, 0.0) and judge_standing(model, qpos, 0.0, ground=0.0)
    assert not judge_standing(model, qpos, 0.5)
    low = qpos.copy()
    low[2] = 0.4
    assert not judge_standing(model, low, 0.0)
    tilted = qpos.copy()
    tilted[3:7] = [np.cos(0.3), np.sin(0.3), 0.0, 0.0]  # 34° about x
    assert not judge_standing(model, tilted, 0.0)
    # standing on the floor where the reference ends on a 5 cm step: not where the task ends
    assert not judge_standing(model, qpos, 0.0, ground=0.05)


def test_the_reference_ends_on_the_step_it_climbs():
    from pipeline.export.chain import end_ground
    from pipeline.robot.g1 import build_spec

    def step(spec):
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1])
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5, 1.0, 0.1], pos=[1.5, 0.0, 0.1])

    model = build_spec(terrain=step).compile()
    targets = np.zeros((3, 4, 3))
    targets[-1, :, 0] = [1.2, 1.3, 1.4, 1.5]  # the last keyframe's bodies over the step, the others before it
    assert end_ground(model, targets) == pytest.approx(0.2)
    targets[-1, :, 0] = 0.5
    assert end_ground(model, targets) == pytest.approx(0.0)


def test_stance_state_stands_on_the_ground_under_the_start(chain_export):
    from pipeline.export.sim2sim import build_scene

    meta = json.loads((chain_export / "policy.json").read_text())
    model = build_scene(meta, 1.4)
    qpos, qvel = stance_state(meta, model, 0.76)
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    assert qvel.max() == 0 and abs(qpos[2] - 0.76) < 1e-9  # flat start


def test_an_export_without_its_balance_policy_is_refused(chain_export, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(chain_export, bare)
    (bare / CHAIN_NAME).unlink()
    with pytest.raises(PipelineInputError, match="chain.json.*no balance policy"):
        ChainRunner(bare)
    missing = tmp_path / "missing"
    shutil.copytree(chain_export, missing)
    shutil.rmtree(missing / "balance")
    with pytest.raises(PipelineInputError, match="balance.*holds no balance policy.onnx"):
        read_chain(missing)


def test_a_handoff_past_the_end_of_the_task_is_refused(chain_export, tmp_path):
    late = tmp_path / "late"
    shutil.copytree(chain_export, late)
    chain = json.loads((late / CHAIN_NAME).read_text())
    (late / CHAIN_NAME).write_text(json.dumps(dict(chain, handoff_phase=1.2)))
    with pytest.raises(PipelineInputError, match="handoff_phase.*past the end of the task"):
        ChainRunner(late)


def test_export_without_the_balance_export_writes_nothing(tmp_path):
    from pipeline.export.onnx_export import export_folder

    with pytest.raises(PipelineInputError, match="balance policy's export is missing"):
        export_folder(*_standin_task(), tmp_path / "out", balance_export=tmp_path / "nowhere")
    assert not (tmp_path / "out").exists()


def test_delayed_targets_apply_what_was_sent_that_long_ago():
    from pipeline.export.chain import DelayedTargets

    delay = DelayedTargets(0.012, 0.005)  # 2 substeps (rounded)
    delay.hold(np.zeros(1))
    applied = []
    for step in range(3):
        delay.send(np.array([step + 1.0]))
        applied += [float(delay.applied()[0]) for _ in range(4)]
    assert applied == [0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3]


def test_a_handoff_before_the_last_keyframe_judges_the_keyframes_up_to_it():
    """The keyframes after a chain's handoff belong to no policy: the success test stops at the handoff."""
    from pipeline.export.sim2sim import EpisodeJudge

    meta = {"keyframes": {"phases": [0.3, 0.6, 0.9]}, "phase": {"num_frames": 10},
            "terminations": {"max_tilt": 10.0, "min_base_height": 0.0}, "success_threshold_m": 1.0}
    targets = np.zeros((3, 2, 3))
    judge = EpisodeJudge(meta, 0.0, targets)
    near, far = np.full((2, 3), 0.1), np.full((2, 3), 3.0)
    judge.update(0.35, near, np.zeros(3), 0.8)
    assert not judge.success_through(0.65)  # the keyframe at 0.6 is due and not reached
    judge.update(0.65, near, np.zeros(3), 0.8)
    assert judge.success_through(0.65) and judge.success_through(0.6)
    assert not judge.success  # the whole test still asks for the last keyframe
    judge.update(0.95, far, np.zeros(3), 0.8)
    assert judge.success_through(0.65) and not judge.success_through(1.0) and not judge.success
    assert not EpisodeJudge(meta, 0.0, targets).success_through(0.1)  # no keyframe due: nothing to succeed at


def test_a_task_declares_its_handoff_after_its_last_landing():
    from types import SimpleNamespace

    from pipeline.export.chain import handoff_phase
    from pipeline.keyframes.config import TaskConfig

    motion = SimpleNamespace(num_frames=101, fps=50.0)
    data = SimpleNamespace(task="hop", motion=motion, keyframe_frames=[20, 50, 60],
                           keyframe_labels=("takeoff", "landing", ""))
    assert handoff_phase(data, None) == 1.0
    assert handoff_phase(data, 0.2) == pytest.approx((50 + 10) / 100)
    assert handoff_phase(data, 5.0) == 1.0  # never past the task's end
    with pytest.raises(PipelineInputError, match="landing"):
        handoff_phase(SimpleNamespace(task="wave", motion=motion, keyframe_frames=[10], keyframe_labels=("",)), 0.1)

    far = {"input": "x.npz", "edit": "x", "psi": {"raw": 1.1, "easy": [[0.7, 1.6]]}}
    task = TaskConfig.from_dict("hop", {**far, "clip": {"handoff_after_landing_s": 0.1}})
    assert task.clip.handoff_after_landing_s == 0.1 and TaskConfig.from_dict("hop", far).clip.handoff_after_landing_s is None
    with pytest.raises(PipelineInputError, match="clip.handoff_after_landing_s"):
        TaskConfig.from_dict("hop", {**far, "clip": {"handoff_after_landing_s": -1}})


def test_chain_eval_refuses_a_folder_without_its_export_or_metrics(chain_export, tmp_path, capsys):
    """`python -m pipeline.evaluation.chain_eval FOLDER`: one line naming the missing file, exit 2, nothing written."""
    from pipeline.evaluation.chain_eval import main

    folder = tmp_path / "policy"
    shutil.copytree(chain_export, folder / "export")
    assert main([str(folder)]) == 2
    assert f"{folder / 'metrics.json'}: missing" in capsys.readouterr().err
    assert sorted(p.name for p in folder.iterdir()) == ["export"]
