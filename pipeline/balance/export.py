"""The balance policy as a deployable folder, like every policy: policy.onnx + policy.json + hub format.

Its policy.json has `kind: balance`, the robot block, the proprioceptive observation layout (no phase,
ψ or odometry terms), the fall checks it was trained against and the standing test. The ONNX graph
has the same inputs and outputs as a task policy's (`phase_rate_offset` is always 0), so one step
function (`export.policy_step.PolicyStepper`) runs either.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.balance.config import BalanceConfig
from pipeline.common.errors import PipelineInputError
from pipeline.envs.falls import STANDING
from pipeline.export.metadata import METADATA_VERSION, observation_layout
from pipeline.export.onnx_export import DeployedPolicy, ExportResult, export_folder

BALANCE_KIND = "balance"


def proprio_terms(robot) -> list[dict]:
    """The balance env's observation, one step (`RobotEnv._proprio`'s order)."""
    j = robot.num_joints
    return [
        {"name": "base_ang_vel", "dim": 3, "scale": 1.0},
        {"name": "projected_gravity", "dim": 3, "scale": 1.0},
        {"name": "joint_pos", "dim": j, "scale": 1.0, "offset": robot.default_joint_pos.tolist()},
        {"name": "joint_vel", "dim": j, "scale": 1.0},
        {"name": "last_action", "dim": j, "scale": 1.0},
    ]


def balance_metadata(cfg: BalanceConfig, robot) -> dict:
    env = cfg.env
    return {
        "metadata_version": METADATA_VERSION,
        "kind": BALANCE_KIND,
        "task": "balance",
        "variant": "balance",
        **robot.metadata(),
        "control_rate_hz": 1.0 / robot.control_dt,
        "tracked_site_names": list(robot.tracked_site_names),
        "observation": observation_layout(robot, env.observations.history, proprio_terms(robot)),
        "action_offset": "default",
        "outputs": {"joint_targets": "default_joint_pos + action_scale * action",
                    "action": "raw action a (next step's last_action)", "phase_rate_offset": "always 0"},
        # the stepper's phase bookkeeping: a balance policy has no phase (rate 0, no bounds)
        "phase": {"rate": 0.0, "offset_bounds": [0.0, 0.0]},
        "terminations": {"max_tilt": env.terminations.max_tilt, "min_base_height": env.terminations.min_base_height,
                         "relative_to_reference": False, "base_height_applies": True},
        "standing": {"max_tilt": STANDING.max_tilt, "min_height": STANDING.min_height, "max_speed": STANDING.max_speed},
        "stance": {"root_height": robot.default_root_height},
        "physics": env.physics,
        "sim_dt": robot.physics(env.physics).timestep,
    }


def export_balance(cfg: BalanceConfig, policy_dir: str | Path, out_dir: str | Path) -> ExportResult:
    from pipeline.rl.checkpoint import load_policy
    from pipeline.robot.g1 import load_robot_config

    robot = load_robot_config()
    policy_dir = Path(policy_dir)
    if not (policy_dir / "config.json").is_file():
        raise PipelineInputError(policy_dir, None, "trained balance policy not found (config.json + model.safetensors)")
    module, meta = load_policy(policy_dir, expect={"robot": robot.name, "joint_names": list(robot.joint_names)})
    if meta.get("task") != "balance":
        raise PipelineInputError(policy_dir / "config.json", "task", f"is {meta.get('task')!r}, not a balance policy")
    metadata = balance_metadata(cfg, robot)
    if metadata["observation"]["dim"] != meta["actor_obs_dim"]:
        raise PipelineInputError(policy_dir / "config.json", "actor_obs_dim",
                                 f"{meta['actor_obs_dim']} does not match the balance layout ({metadata['observation']['dim']})")
    from pipeline.envs.balance_env import balance_actuation

    stance_target, action_scale = balance_actuation(cfg.env, robot)
    metadata["action_scale"] = action_scale.tolist()
    metadata["stance"]["joint_target"] = stance_target.tolist()
    metadata["outputs"]["joint_targets"] = "stance.joint_target + action_scale * action (frozen joints: scale 0)"
    deployed = DeployedPolicy(module, stance_target, action_scale)
    return export_folder(deployed, metadata["observation"]["dim"], metadata, out_dir, source_dir=policy_dir)
