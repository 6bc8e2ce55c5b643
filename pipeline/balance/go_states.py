"""Where the balance policy holds the robot when the go comes: the states a task policy really starts from.

A chain stands `stand_s` on the balance policy from the stance at rest before the task policy takes over
(`pipeline/export/chain.py`). By then the robot is not in the stance a task's lead-in begins with: the
balance policy has bent the joints by tenths of a radian, turned and shifted the base a little, and under
the randomised model it sways. A task policy trained only from the exact stance meets at the go a start it
has never seen. `record_go_states` stands the balance policy `stands` times on flat ground (the first on the
nominal model, the rest under the paper's randomisation) and keeps the state at the go, as a displacement
from the stance (position and velocity in the stance's heading frame, the base's orientation relative to
the stance's heading), so that `env.go_starts` can put it at any task's stance (`pipeline/envs/go_starts.py`).
Stands that fall are left out.
"""

from __future__ import annotations

import copy
from pathlib import Path

import mujoco
import numpy as np

from pipeline.common.errors import PipelineInputError

DEFAULT_STAND_S = 2.0  # the chain's own (export/chain.py DEFAULT_CHAIN)


def record_go_states(balance_export: str | Path, stands: int, *, stand_s: float = DEFAULT_STAND_S,
                     seed: int = 0) -> dict[str, np.ndarray]:
    """{"qpos" (M, nq), "qvel" (M, nv)}: the robot at the go of `stands` stands, relative to the stance at
    rest at the origin facing +x: qpos[0:3] is the root's displacement from the stance's root. Torch's
    global RNG is left as it was."""
    import torch

    from pipeline.envs.config import RandomizationConfig
    from pipeline.evaluation.chain_eval import model_randomizer
    from pipeline.export.chain import DelayedTargets, balance_fallen, control_step
    from pipeline.export.policy_step import PolicyStepper
    from pipeline.export.sim2sim import RobotState, build_scene, load_exported

    session, meta = load_exported(balance_export)
    if meta.get("kind") != "balance":
        raise PipelineInputError(Path(balance_export) / "policy.json", "kind", "is not a balance policy")
    stepper = PolicyStepper(session, meta)
    nominal = build_scene(meta, 0.0)  # the balance export names no terrain: flat ground
    decimation = int(round(meta["control_dt"] / meta["sim_dt"]))
    steps = int(round(stand_s / float(meta["control_dt"])))
    randomize = model_randomizer(RandomizationConfig())
    joints = [nominal.joint(n).id for n in meta["joint_names"]]
    qpos_adr, dof_adr = nominal.jnt_qposadr[joints], nominal.jnt_dofadr[joints]
    actuators = np.array([nominal.actuator(n).id for n in meta["joint_names"]])
    stance_height = float(meta["stance"]["root_height"])
    rows = {"qpos": [], "qvel": []}
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        for stand in range(stands):
            model = copy.deepcopy(nominal)
            delay = DelayedTargets(randomize(model) if stand else 0.0, model.opt.timestep)
            data = mujoco.MjData(model)
            state = RobotState(model, data, qpos_adr, dof_adr)
            data.qpos[2], data.qpos[3], data.qpos[7:] = stance_height, 1.0, meta["default_joint_pos"]
            mujoco.mj_forward(model, data)
            delay.hold(data.qpos[7:])
            stepper.reset()
            for _ in range(steps):
                control_step(stepper, state, delay, actuators, decimation, psi=0.0)
                if balance_fallen(model, data.qpos, meta["terminations"]) is not None:
                    break  # a fallen stand is no start
            else:
                qpos = data.qpos.copy()
                qpos[2] -= stance_height
                rows["qpos"].append(qpos)
                rows["qvel"].append(data.qvel.copy())
    if not rows["qpos"]:
        raise PipelineInputError(balance_export, None, f"the balance policy fell in every one of {stands} stands")
    return {k: np.asarray(v) for k, v in rows.items()}
