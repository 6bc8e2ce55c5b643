"""What the balance policy makes of the state a task hands it: the catch estimate a chained task is paid at its handoff.

A chain hands the robot to the balance policy at its handoff point (export/chain.py `handoff_phase`), and
the balance policy either catches it or falls. Its own critic already knows which: the sparse group of the
balance env is the fall penalty alone (`termination`, −200, γ 0.99), so that critic's value of a state is
the penalty times the discounted chance of falling from it, over a horizon of about 2 s. One minus their
ratio is the balance policy's estimate of catching the robot:

    catch(s) = clamp(1 − V_sparse(s) / termination, 0, 1)       1: it stands, 0: it falls at once

On 196 starts drawn from the 98 states the far jump's chains hand `balance_far_jump` over in (its
`start_states`, nominal model, no pushes), this estimate told the 21 the policy held for 3 s from the 175
it dropped with an AUC of 0.99 (its dense critic's value: 0.01, the wrong way round). A task trained with `env.rewards.weights.handoff_catch` > 0
ends its episodes at the chain's handoff and is paid `handoff_catch · catch(s)` there, the way skill
chaining makes one skill end inside the next one's starting set.

The state is read as the balance env reads a recorded start (`BalanceEnv._reset_worlds`): a history
filled with the first frame, no last action, feet contacts not yet known, the pelvis's height above the
ground under it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.balance_env import balance_features
from pipeline.envs.torch_math import projected_gravity


@dataclass(frozen=True)
class Handoff:
    """Where a chained task hands over and to whom: the phase (export/chain.py `handoff_phase`) and the
    balance policy's training checkpoint folder (`<balance.out>/train/policy`: config.json and weights
    with its critic)."""

    phase: float
    balance_checkpoint: Path


class HandoffCatch:
    """catch(qpos, qvel, ground) -> (N,) in [0, 1], by the frozen critic of the balance policy."""

    def __init__(self, checkpoint: str | Path, default_joint_pos: torch.Tensor, device="cpu"):
        from pipeline.rl.checkpoint import load_policy

        checkpoint = Path(checkpoint)
        if not (checkpoint / "config.json").is_file():
            raise PipelineInputError(checkpoint, "config.json", "no balance policy checkpoint here (the handoff "
                                     "catch reads the balance policy's critic from <balance.out>/train/policy)")
        _, critic, meta = load_policy(checkpoint, with_critic=True)
        layout = meta.get("obs_layout") or {}
        frame_dim, history = layout.get("frame_dim"), layout.get("history")
        privileged = layout.get("critic_privileged") or {}
        if meta.get("task") != "balance" or not frame_dim or not history or "base_height" not in privileged:
            raise PipelineInputError(checkpoint / "config.json", "obs_layout",
                                     "not a balance policy's checkpoint (no balance observation layout)")
        termination = float(((meta.get("env_config") or {}).get("rewards") or {}).get("weights", {}).get("termination", 0.0))
        if not termination < 0:
            raise PipelineInputError(checkpoint / "config.json", "env_config.rewards.weights.termination",
                                     f"the catch estimate needs a negative fall penalty, got {termination}")
        self.critic = critic.to(device).eval()
        for p in self.critic.parameters():
            p.requires_grad_(False)
        self.termination = termination
        self.history = int(history)
        self.num_joints = int(default_joint_pos.numel())
        if frame_dim != 6 + 3 * self.num_joints or meta.get("critic_obs_dim") != frame_dim * history + 6:
            raise PipelineInputError(checkpoint / "config.json", "critic_obs_dim",
                                     f"expected {self.num_joints} joints' proprioception, got frame {frame_dim}, "
                                     f"critic {meta.get('critic_obs_dim')}")
        self.default_joint_pos = default_joint_pos.to(device)

    def observation(self, qpos: torch.Tensor, qvel: torch.Tensor, ground: torch.Tensor) -> torch.Tensor:
        """(N, critic_obs_dim): the balance critic's observation of a fresh start in these states; `ground`
        (N,) the height of the ground the robot stands on."""
        on_flat_ground = qpos.clone()
        on_flat_ground[:, 2] -= ground  # the balance env's floor is at 0
        no_contact = torch.zeros(qpos.shape[0], 2, dtype=torch.bool, device=qpos.device)
        frame, privileged = balance_features(on_flat_ground, qvel, projected_gravity(qpos[:, 3:7]), no_contact,
                                             torch.zeros_like(qpos[:, 7:]), self.default_joint_pos)
        return torch.cat([frame.repeat(1, self.history), privileged], -1)

    @torch.no_grad()
    def __call__(self, qpos: torch.Tensor, qvel: torch.Tensor, ground: torch.Tensor) -> torch.Tensor:
        v_sparse, _ = self.critic(self.observation(qpos, qvel, ground))
        return (1.0 - v_sparse.reshape(-1) / self.termination).clamp(0.0, 1.0)


__all__ = ["Handoff", "HandoffCatch"]
