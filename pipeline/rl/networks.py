"""Networks: MLPs, an empirical observation normaliser, the stage-1 Gaussian actor, the double critic.

Every policy module maps an actor observation to a deterministic (joint action, Δφ^Δ) in `forward`
so that the export code sees one plain `nn.Module` whatever the stage. Training goes through
`distribution(obs)` over "raw" outputs (the Gaussian's sample space) and `to_env(obs, raw)`, which
turns a raw sample into what the environment receives.
"""

from __future__ import annotations

import math

import torch
from torch import nn

_ACT = {"elu": nn.ELU, "relu": nn.ReLU, "tanh": nn.Tanh, "silu": nn.SiLU}


def mlp(in_dim: int, hidden: list[int], out_dim: int, activation: str = "elu", out_gain: float = 1.0) -> nn.Sequential:
    layers: list[nn.Module] = []
    last = in_dim
    for width in hidden:
        layers += [nn.Linear(last, width), _ACT[activation]()]
        last = width
    head = nn.Linear(last, out_dim)
    # A small last layer keeps initial actions near zero (the action offset: reference or default pose)
    # and values near zero.
    nn.init.orthogonal_(head.weight, gain=out_gain)
    nn.init.zeros_(head.bias)
    layers.append(head)
    return nn.Sequential(*layers)


class EmpiricalNormalizer(nn.Module):
    """Running mean/variance of observations (parallel Welford merge); buffers travel with the policy.

    `pin` fixes chosen columns' statistics: a task parameter the curriculum shows in a narrow band for
    most of a run (ψ) would otherwise be scaled by that band, and the far values met at evaluation
    would reach the network many standard deviations out (see TrackingEnv.pinned_observation_stats)."""

    def __init__(self, dim: int, eps: float = 1e-2, clip: float = 10.0, enabled: bool = True):
        super().__init__()
        self.eps, self.clip, self.enabled = eps, clip, enabled
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("var", torch.ones(dim))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        # Not saved: whoever builds the normaliser pins again; the pinned values travel in mean/var.
        self.register_buffer("pinned", torch.zeros(dim, dtype=torch.bool), persistent=False)

    @torch.no_grad()
    def pin(self, columns: list[int], mean: float | None = None, var: float | None = None) -> None:
        """Fixes `columns` at `mean` and `var` (None: at their current values) for every later update."""
        index = torch.as_tensor(columns, dtype=torch.long, device=self.mean.device)
        if mean is not None:
            self.mean[index] = float(mean)
        if var is not None:
            self.var[index] = float(var)
        self.pinned[index] = True

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        if not self.enabled:
            return
        x = x.reshape(-1, x.shape[-1]).to(self.mean.dtype)
        n = x.shape[0]
        batch_mean = x.mean(0)
        batch_var = x.var(0, unbiased=False)
        total = self.count + n
        delta = batch_mean - self.mean
        frac = float(n / total)
        merged_mean = self.mean + delta * frac
        merged_var = self.var * (1 - frac) + batch_var * frac + delta**2 * frac * (1 - frac)
        self.mean.copy_(torch.where(self.pinned, self.mean, merged_mean))
        self.var.copy_(torch.where(self.pinned, self.var, merged_var))
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.enabled:
            return x
        return ((x - self.mean) / torch.sqrt(self.var + self.eps)).clamp(-self.clip, self.clip)


class PhaseBound(nn.Module):
    """tanh-affine squashing of a raw output into Δφ^Δ ∈ [−0.75Δφ, +Δφ]; raw 0 maps to 0."""

    def __init__(self, phase_rate: float, low_fraction: float = 0.75):
        super().__init__()
        self.low, self.high = -low_fraction * phase_rate, phase_rate
        # Shift so that raw = 0 lands on Δφ^Δ = 0: tanh(shift) = -(high + low) / (high - low).
        self.shift = math.atanh(-(self.high + self.low) / (self.high - self.low))

    def forward(self, raw: torch.Tensor) -> torch.Tensor:
        unit = (torch.tanh(raw + self.shift) + 1.0) * 0.5
        return self.low + unit * (self.high - self.low)


class Stage1Policy(nn.Module):
    """Gaussian actor with a state-independent log-std. With `adaptive_phase` one more output is the
    phase-rate offset (variants *_dphi); otherwise Δφ^Δ is always 0.

    `output_bound` > 0 squashes the mean into ±bound (bound·tanh(x/bound)): the off-policy trainer's
    deterministic actor (fast_td3.py), whose critics must not be asked about actions they never saw.
    Its log-std is then unused; the mean is the policy, here and in stage 2."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: list[int], activation: str = "elu",
                 init_log_std: float = 0.0, adaptive_phase: bool = False, phase_rate: float = 0.01,
                 normalize_obs: bool = True, output_bound: float = 0.0):
        super().__init__()
        self.output_bound = float(output_bound)
        self.obs_dim, self.action_dim, self.adaptive_phase = obs_dim, action_dim, adaptive_phase
        self.raw_dim = action_dim + int(adaptive_phase)
        self.normalizer = EmpiricalNormalizer(obs_dim, enabled=normalize_obs)
        self.body = mlp(obs_dim, hidden, self.raw_dim, activation, out_gain=0.01)
        self.log_std = nn.Parameter(torch.full((self.raw_dim,), float(init_log_std)))
        self.phase_bound = PhaseBound(phase_rate)

    def raw_mean(self, obs: torch.Tensor) -> torch.Tensor:
        out = self.body(self.normalizer(obs))
        if self.output_bound > 0:
            return self.output_bound * torch.tanh(out / self.output_bound)
        return out

    def distribution(self, obs: torch.Tensor) -> torch.distributions.Normal:
        mean = self.raw_mean(obs)
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean))

    def sample(self, obs: torch.Tensor, noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(raw, log_prob). `noise`: a standard-normal ε to use (exploration.CorrelatedNoise) instead of a fresh draw."""
        dist = self.distribution(obs)
        raw = dist.sample() if noise is None else dist.mean + dist.stddev * noise
        return raw, dist.log_prob(raw).sum(-1)

    def log_prob_entropy(self, obs: torch.Tensor, raw: torch.Tensor):
        dist = self.distribution(obs)
        return dist.log_prob(raw).sum(-1), dist.entropy().sum(-1), dist.mean, dist.stddev

    def to_env(self, obs: torch.Tensor, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        action = raw[:, : self.action_dim]
        if self.adaptive_phase:
            return action, self.phase_bound(raw[:, -1])
        return action, torch.zeros_like(raw[:, 0])

    def update_normalizers(self, obs: torch.Tensor) -> None:
        self.normalizer.update(obs)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Deterministic deployable policy: (joint action (N, A), Δφ^Δ (N,))."""
        return self.to_env(obs, self.raw_mean(obs))


class ReturnNormalizer(nn.Module):
    """Running mean/std of one reward group's returns (exponential, bias-corrected), so a critic
    head regresses returns of unit scale whatever the group's magnitude (value normalisation as in
    rl_games' `normalize_value` / MAPPO's ValueNorm). Sparse returns here are O(100–1000): a head
    regressing them directly needs thousands of Adam steps just to grow its output layer."""

    def __init__(self, decay: float = 0.99, eps: float = 1e-4, enabled: bool = True):
        super().__init__()
        self.decay, self.eps, self.enabled = decay, eps, enabled
        self.register_buffer("mean", torch.zeros(()))
        self.register_buffer("mean_sq", torch.ones(()))
        self.register_buffer("weight", torch.zeros((), dtype=torch.float64))  # bias correction

    @property
    def std(self) -> torch.Tensor:
        mean, mean_sq = self._debiased()
        return torch.sqrt((mean_sq - mean**2).clamp(min=self.eps))

    def _debiased(self) -> tuple[torch.Tensor, torch.Tensor]:
        if float(self.weight) <= 0.0:
            return self.mean, self.mean_sq  # untouched: identity (mean 0, std 1)
        w = float(self.weight)
        return self.mean / w, self.mean_sq / w

    @torch.no_grad()
    def update(self, returns: torch.Tensor) -> None:
        if not self.enabled:
            return
        x = returns.reshape(-1).to(self.mean.dtype)
        if float(self.weight) <= 0.0:
            self.mean.zero_()
            self.mean_sq.zero_()
        d = self.decay
        self.mean.mul_(d).add_((1 - d) * x.mean())
        self.mean_sq.mul_(d).add_((1 - d) * (x * x).mean())
        self.weight.mul_(d).add_(1 - d)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        if not self.enabled:
            return x
        return (x - self._debiased()[0]) / self.std

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        if not self.enabled:
            return x
        return x * self.std + self._debiased()[0]


class DoubleCritic(nn.Module):
    """Two value networks, one per reward group: sparse keyframe rewards and dense tracking rewards
    live on very different scales and horizons, so one network for both would blur them.

    Each head predicts its group's return normalised by that group's running return statistics;
    `forward` gives values in reward units (for GAE), `normalized` the heads' raw outputs (for the
    regression, which then has unit scale in both groups)."""

    def __init__(self, obs_dim: int, hidden: list[int], activation: str = "elu", normalize_obs: bool = True,
                 normalize_values: bool = True):
        super().__init__()
        self.normalizer = EmpiricalNormalizer(obs_dim, enabled=normalize_obs)
        self.sparse = mlp(obs_dim, hidden, 1, activation)
        self.dense = mlp(obs_dim, hidden, 1, activation)
        self.sparse_returns = ReturnNormalizer(enabled=normalize_values)
        self.dense_returns = ReturnNormalizer(enabled=normalize_values)

    def return_normalizer(self, group: str) -> ReturnNormalizer:
        return self.sparse_returns if group == "sparse" else self.dense_returns

    def normalized(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.normalizer(obs)
        return self.sparse(x).squeeze(-1), self.dense(x).squeeze(-1)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        v_sparse, v_dense = self.normalized(obs)
        return self.sparse_returns.denormalize(v_sparse), self.dense_returns.denormalize(v_dense)

    def update_normalizers(self, obs: torch.Tensor) -> None:
        self.normalizer.update(obs)
