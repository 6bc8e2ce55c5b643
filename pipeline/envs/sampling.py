"""Which D_edit sample (ψ) a world tracks next: uniform, or adaptive to where episodes fail.

Adaptive sampling follows BeyondMimic's idea (there over start times of a long motion, here over the
edited samples): keep a running failure rate per sample and draw the next episodes in proportion to
it, mixed with a uniform share so solved samples are still rehearsed. Training compute then goes
to the edge of what the policy can already do instead of to gaps it clears every time.
"""

from __future__ import annotations

import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import SamplingConfig


class SampleSampler:
    def __init__(self, cfg: SamplingConfig, num_samples: int, device="cpu"):
        self.cfg = cfg
        self.num_samples = num_samples
        # Start pessimistic: every sample is assumed to fail until episodes say otherwise.
        self.failure_rate = torch.ones(num_samples, dtype=torch.float64, device=device)

    def probabilities(self) -> torch.Tensor:
        uniform = torch.full_like(self.failure_rate, 1.0 / self.num_samples)
        if self.cfg.mode == "uniform":
            return uniform
        total = float(self.failure_rate.sum())
        if total <= 0.0:
            return uniform
        u = self.cfg.uniform_ratio
        return u * uniform + (1.0 - u) * self.failure_rate / total

    def draw(self, n: int) -> torch.Tensor:
        if self.cfg.mode == "uniform":
            return torch.randint(self.num_samples, (n,), device=self.failure_rate.device)
        return torch.multinomial(self.probabilities(), n, replacement=True)

    def record(self, samples: torch.Tensor, failed: torch.Tensor) -> None:
        """Episodes that ended this step: their sample index and whether they failed (adaptive mode only)."""
        if self.cfg.mode != "adaptive" or samples.numel() == 0:
            return
        count = torch.zeros_like(self.failure_rate).index_add_(0, samples, torch.ones_like(samples, dtype=torch.float64))
        fails = torch.zeros_like(self.failure_rate).index_add_(0, samples, failed.to(torch.float64))
        seen = count > 0
        # One EMA step per episode, several episodes of one sample in one step count together.
        step = (self.cfg.rate * count).clamp(max=1.0)
        self.failure_rate = torch.where(seen, self.failure_rate + step * (fails / count.clamp(min=1) - self.failure_rate),
                                        self.failure_rate)

    def state_dict(self) -> dict:
        return {"failure_rate": self.failure_rate.detach().cpu().clone()}

    def load_state_dict(self, state: dict) -> None:
        saved = state["failure_rate"]
        if saved.shape != self.failure_rate.shape:
            raise PipelineInputError("env state", "sampler.failure_rate",
                                     f"expected {tuple(self.failure_rate.shape)}, got {tuple(saved.shape)}")
        self.failure_rate = saved.to(self.failure_rate.device, torch.float64).clone()
