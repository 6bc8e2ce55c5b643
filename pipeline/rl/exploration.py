"""Exploration noise that is correlated in time, for `ppo.noise_correlation` > 0.

PPO samples each action as mean + std · ε. The paper's ε is white: drawn anew at every 20 ms step. A
jump's push-off is a joint offset held over tenths of a second (benchmarks/RESULTS.md, jump_ceiling.py),
and white noise averages out over such a span: 25 steps of it move a push by 1/5 of one step's noise.
Here ε follows a first-order autoregressive process per world,

    ε_t = ρ · ε_{t−1} + √(1 − ρ²) · ξ_t,   ξ_t ~ N(0, 1),   ε_0 ~ N(0, 1) at each episode's start,

so every ε_t is still N(0, 1): the action's marginal distribution is the policy's own Gaussian, and PPO's
log-probabilities, ratios and entropy are computed as with white noise. What changes is that successive
steps explore together over about 1/(1 − ρ) steps. This is the "colored noise" of Hollenstein et al.
(AAAI 2024) in its simplest form; ρ = 0 is white noise (and the trainer then draws it as before).
"""

from __future__ import annotations

import math

import torch


class CorrelatedNoise:
    """ε (num_worlds, dim) for the next action, restarted for worlds whose episode ended."""

    def __init__(self, num_worlds: int, dim: int, correlation: float, device):
        if not 0.0 <= correlation < 1.0:
            raise ValueError(f"noise correlation must be in [0, 1), got {correlation}")
        self.correlation = float(correlation)
        self.innovation_scale = math.sqrt(1.0 - self.correlation**2)
        self.epsilon = torch.randn(num_worlds, dim, device=device)

    def next(self) -> torch.Tensor:
        """The ε to act with now; the process then advances one step."""
        current = self.epsilon
        self.epsilon = self.correlation * current + self.innovation_scale * torch.randn_like(current)
        return current

    def restart(self, ended: torch.Tensor | None = None) -> None:
        """Fresh, independent ε for the worlds whose episode ended (all worlds when None)."""
        fresh = torch.randn_like(self.epsilon)
        self.epsilon = fresh if ended is None else torch.where(ended.unsqueeze(-1), fresh, self.epsilon)

    def state_dict(self) -> dict:
        return {"epsilon": self.epsilon.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.epsilon = state["epsilon"].to(self.epsilon.device).clone()
