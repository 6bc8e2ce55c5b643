"""Episodes from t = 0 that begin where the balance policy holds the robot at the go (`env.go_starts`).

A task's reference begins in the stance at rest (its lead-in, `pipeline/keyframes/lead_in.py`), and a
start at t = 0 puts the robot exactly there, still. A chain's go comes after `stand_s` on the balance
policy: joints bent by tenths of a radian, the base turned a few degrees, swaying under the randomised
model (`pipeline/balance/go_states.py` records such states). With `prob` > 0 that share of the starts at
t = 0 begins in one of them instead, placed at the task's stance (its position and heading), and the
robot's odometry counts from there, as the chain's does from the pose at the go. Stage 2 keeps them
(they are starts at t = 0); the evaluate stage's batch does not (it scores from the stance), the chains
do by construction. The training stages do not list the balance export among their DVC dependencies (a
task with go starts off, the sample's default, must not retrain when the balance policy changes): after a
new `balance.out`, force a task that uses go starts (`dvc repro -f -s train_stage1@<task>-<variant>`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.torch_math import quat_mul, quat_rotate


@dataclass
class GoStartConfig:
    prob: float = 0.0  # share of the starts at t = 0 (0: off, every start at the exact stance)
    stands: int = 64  # stands recorded on the balance policy of params.yaml `balance.out` (the first nominal)
    stand_s: float = 2.0  # the chain's stand before the go (export/chain.py)

    def validate(self, where: str) -> None:
        if not 0.0 <= self.prob <= 1.0:
            raise PipelineInputError(where, "go_starts.prob", "must be in [0, 1]")
        if self.stands < 1:
            raise PipelineInputError(where, "go_starts.stands", "must be >= 1")
        if not self.stand_s > 0:
            raise PipelineInputError(where, "go_starts.stand_s", "must be > 0 (s)")


class GoStates:
    """Recorded go states (`pipeline/balance/go_states.py`: relative to a stance at the origin facing +x,
    qpos[0:3] the root's displacement from the stance's) on the env's device."""

    def __init__(self, states: dict, nq: int, nv: int, device, source: str = "go states"):
        qpos, qvel = np.asarray(states["qpos"]), np.asarray(states["qvel"])
        if qpos.ndim != 2 or qpos.shape[1] != nq or len(qpos) == 0:
            raise PipelineInputError(source, "qpos", f"expected (M >= 1, {nq}) rows, got {qpos.shape}")
        if qvel.shape != (len(qpos), nv):
            raise PipelineInputError(source, "qvel", f"expected ({len(qpos)}, {nv}), got {qvel.shape}")
        self.qpos = torch.as_tensor(qpos, dtype=torch.float32, device=device)
        self.qvel = torch.as_tensor(qvel, dtype=torch.float32, device=device)

    def __len__(self) -> int:
        return int(self.qpos.shape[0])

    def place(self, n: int, stance_pos: torch.Tensor, stance_yaw_quat: torch.Tensor):
        """(qpos, qvel) of `n` drawn go states at a stance: `stance_pos` (3,) its root position,
        `stance_yaw_quat` (4,) its heading."""
        pick = torch.randint(len(self), (n,), device=self.qpos.device)
        qpos, qvel = self.qpos[pick].clone(), self.qvel[pick].clone()
        heading = stance_yaw_quat.to(qpos.dtype).expand(n, 4)
        qpos[:, 0:3] = stance_pos.to(qpos.dtype) + quat_rotate(heading, qpos[:, 0:3])
        qpos[:, 3:7] = quat_mul(heading, qpos[:, 3:7])
        qvel[:, 0:3] = quat_rotate(heading, qvel[:, 0:3])  # world frame; the angular part is the base's own
        return qpos, qvel
