"""AMP baselines (amp_style, amp_mimic): a least-squares discriminator on short joint-position windows.

The discriminator D sees `window` consecutive joint-position frames (amp_mimic: plus the phase of the
window's last frame). It is trained towards +1 on windows of the reference motion and −1 on windows
the policy produced (LSGAN, as AMP), with a gradient penalty on the reference windows. The style
reward is max(0, 1 − ¼(D − 1)²) ∈ [0, 1]; the task groups are scaled by `task_weight` (0.9) and the
style reward, times `style_weight` (0.1), is added to the sparse group.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from pipeline.rl.config import AMPConfig
from pipeline.rl.networks import EmpiricalNormalizer, mlp


def reference_windows(joint_pos: np.ndarray, window: int, with_phase: bool) -> torch.Tensor:
    """All windows of `window` consecutive frames of a reference (T, J) -> (T-window+1, window*J [+1])."""
    frames = joint_pos.shape[0]
    if frames < window:
        raise ValueError(f"reference has {frames} frames, fewer than the AMP window {window}")
    starts = np.arange(frames - window + 1)
    windows = np.stack([joint_pos[s : s + window].reshape(-1) for s in starts])
    if with_phase:
        phase = (starts + window - 1) / max(frames - 1, 1)
        windows = np.concatenate([windows, phase[:, None]], axis=1)
    return torch.as_tensor(windows, dtype=torch.float32)


class JointWindow:
    """Per-env ring of the last `window` joint-position frames; reset envs are filled with their
    first frame so every window is a plausible one."""

    def __init__(self, num_envs: int, num_joints: int, window: int, device="cpu"):
        self.frames = torch.zeros(num_envs, window, num_joints, device=device)
        self.filled = torch.zeros(num_envs, dtype=torch.bool, device=device)

    def push(self, joint_pos: torch.Tensor, reset: torch.Tensor | None = None) -> None:
        if reset is not None:
            self.filled &= ~reset
        fresh = ~self.filled
        self.frames = torch.roll(self.frames, -1, dims=1)
        self.frames[:, -1] = joint_pos
        self.frames[fresh] = joint_pos[fresh].unsqueeze(1).expand(-1, self.frames.shape[1], -1)
        self.filled |= True

    def flat(self, phase: torch.Tensor | None = None) -> torch.Tensor:
        x = self.frames.reshape(self.frames.shape[0], -1)
        return x if phase is None else torch.cat([x, phase.reshape(-1, 1)], -1)


class AMPDiscriminator(nn.Module):
    def __init__(self, input_dim: int, cfg: AMPConfig, activation: str = "elu"):
        super().__init__()
        self.cfg = cfg
        self.normalizer = EmpiricalNormalizer(input_dim)
        self.net = mlp(input_dim, cfg.hidden, 1, activation)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=cfg.learning_rate)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(self.normalizer(x)).squeeze(-1)

    @torch.no_grad()
    def style_reward(self, policy_windows: torch.Tensor) -> torch.Tensor:
        d = self(policy_windows)
        return (1.0 - 0.25 * (d - 1.0) ** 2).clamp(min=0.0)

    def combine(self, rewards: dict[str, torch.Tensor], style: torch.Tensor) -> dict[str, torch.Tensor]:
        return {
            "sparse": self.cfg.task_weight * rewards["sparse"] + self.cfg.style_weight * style,
            "dense": self.cfg.task_weight * rewards["dense"],
        }

    def update(self, reference: torch.Tensor, policy_windows: torch.Tensor, steps: int = 5) -> dict[str, float]:
        """A few LSGAN steps on random batches of reference and policy windows."""
        self.normalizer.update(policy_windows)
        stats = {"disc_loss": 0.0, "disc_real": 0.0, "disc_fake": 0.0}
        batch = min(self.cfg.batch_size, policy_windows.shape[0])
        for _ in range(steps):
            real = reference[torch.randint(reference.shape[0], (batch,), device=reference.device)]
            fake = policy_windows[torch.randint(policy_windows.shape[0], (batch,), device=policy_windows.device)]
            real = real.clone().requires_grad_(True)
            d_real, d_fake = self(real), self(fake)
            loss = 0.5 * ((d_real - 1.0) ** 2).mean() + 0.5 * ((d_fake + 1.0) ** 2).mean()
            grad = torch.autograd.grad(d_real.sum(), real, create_graph=True)[0]
            loss = loss + 0.5 * self.cfg.grad_penalty * (grad**2).sum(-1).mean()
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            stats["disc_loss"] += loss.item() / steps
            stats["disc_real"] += d_real.mean().item() / steps
            stats["disc_fake"] += d_fake.mean().item() / steps
        return stats
