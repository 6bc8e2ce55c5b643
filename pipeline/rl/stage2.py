"""Stage 2: phase and tracking adapters on top of a frozen stage-1 policy.

    Δφ^Δ = π_phase^Δ(o)                        bounded to [−0.75Δφ, +Δφ] (tanh-affine)
    a^Δ  = π_track^Δ(o, Δφ^Δ)
    a    = π_1(o) + (Δφ^Δ / Δφ) · a^Δ          applied joint action

The paper writes the product as Δφ^Δ·a^Δ. Δφ^Δ in phase-per-step units is ~1e-2, which would make
the adapter's Gaussian (and its exploration) a hundred times smaller than the actions it must shape;
we multiply by the *relative* rate change Δφ^Δ/Δφ ∈ [−0.75, 1] instead. That is the same function up
to a constant the adapter absorbs, and it keeps the defining property: at Δφ^Δ = 0 the applied action
is exactly the stage-1 action.

PPO sees the adapters as one Gaussian over raw outputs (u_phase, a^Δ): u_phase is sampled first and
the tracking adapter is conditioned on its bounded value, so the joint log-probability is the sum of
the two factors.
"""

from __future__ import annotations

import torch
from torch import nn

from pipeline.rl.networks import EmpiricalNormalizer, PhaseBound, Stage1Policy, mlp


class Stage2Policy(nn.Module):
    def __init__(self, base: Stage1Policy, hidden: list[int], activation: str = "elu",
                 init_log_std: float = -1.0, freeze_base: bool = True, phase_rate: float = 0.01,
                 normalize_obs: bool = True):
        super().__init__()
        self.base = base
        self.freeze_base = freeze_base
        self.obs_dim, self.action_dim = base.obs_dim, base.action_dim
        self.raw_dim = 1 + self.action_dim
        self.phase_rate = float(phase_rate)
        self.normalizer = EmpiricalNormalizer(self.obs_dim, enabled=normalize_obs)
        self.phase_adapter = mlp(self.obs_dim, hidden, 1, activation, out_gain=0.01)
        self.track_adapter = mlp(self.obs_dim + 1, hidden, self.action_dim, activation, out_gain=0.01)
        self.log_std = nn.Parameter(torch.full((self.raw_dim,), float(init_log_std)))
        self.phase_bound = PhaseBound(self.phase_rate)
        self.set_base_frozen(freeze_base)

    def set_base_frozen(self, frozen: bool) -> None:
        self.freeze_base = frozen
        for p in self.base.parameters():
            p.requires_grad_(not frozen)

    def train(self, mode: bool = True):
        super().train(mode)
        if self.freeze_base:
            self.base.eval()  # a frozen base never changes, in any mode
        return self

    def _base_action(self, obs: torch.Tensor) -> torch.Tensor:
        if self.freeze_base:
            with torch.no_grad():
                return self.base(obs)[0]
        return self.base(obs)[0]

    def _relative_rate(self, u_phase: torch.Tensor) -> torch.Tensor:
        return self.phase_bound(u_phase) / self.phase_rate  # Δφ^Δ / Δφ ∈ [−0.75, 1]

    def _means(self, obs: torch.Tensor, u_phase: torch.Tensor | None):
        x = self.normalizer(obs)
        phase_mean = self.phase_adapter(x).squeeze(-1)
        u = phase_mean if u_phase is None else u_phase
        track_mean = self.track_adapter(torch.cat([x, self._relative_rate(u).unsqueeze(-1)], -1))
        return phase_mean, track_mean

    def raw_mean(self, obs: torch.Tensor) -> torch.Tensor:
        phase_mean, track_mean = self._means(obs, None)
        return torch.cat([phase_mean.unsqueeze(-1), track_mean], -1)

    def sample(self, obs: torch.Tensor, noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Sequential sample: u_phase, then a^Δ given it. Returns (raw, log_prob). `noise`: standard-normal
        ε (N, raw_dim) to use instead of fresh draws."""
        std = self.log_std.exp()
        phase_mean, _ = self._means(obs, None)
        phase_noise = torch.randn_like(phase_mean) if noise is None else noise[:, 0]
        u_phase = phase_mean + std[0] * phase_noise
        _, track_mean = self._means(obs, u_phase)
        track_noise = torch.randn_like(track_mean) if noise is None else noise[:, 1:]
        a_delta = track_mean + std[1:] * track_noise
        raw = torch.cat([u_phase.unsqueeze(-1), a_delta], -1)
        return raw, self.log_prob_entropy(obs, raw)[0]

    def distribution_given(self, obs: torch.Tensor, raw: torch.Tensor) -> torch.distributions.Normal:
        phase_mean, track_mean = self._means(obs, raw[:, 0])
        mean = torch.cat([phase_mean.unsqueeze(-1), track_mean], -1)
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean))

    def log_prob_entropy(self, obs: torch.Tensor, raw: torch.Tensor):
        dist = self.distribution_given(obs, raw)
        return dist.log_prob(raw).sum(-1), dist.entropy().sum(-1), dist.mean, dist.stddev

    def to_env(self, obs: torch.Tensor, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        dphi = self.phase_bound(raw[:, 0])
        action = self._base_action(obs) + (dphi / self.phase_rate).unsqueeze(-1) * raw[:, 1:]
        return action, dphi

    def compose(self, obs: torch.Tensor, dphi: torch.Tensor, a_delta: torch.Tensor) -> torch.Tensor:
        """The applied action for a given Δφ^Δ and a^Δ (used by tests and analysis)."""
        return self._base_action(obs) + (dphi / self.phase_rate).unsqueeze(-1) * a_delta

    def update_normalizers(self, obs: torch.Tensor) -> None:
        self.normalizer.update(obs)
        if not self.freeze_base:
            self.base.update_normalizers(obs)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Deterministic deployable policy: (joint action (N, A), Δφ^Δ (N,))."""
        return self.to_env(obs, self.raw_mean(obs))
