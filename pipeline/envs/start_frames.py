"""Which reference frame a reference-state start begins at (`EnvConfig.rsi_sampling`).

* uniform — any frame of the start table (the stance frames) equally often: the default.
* adaptive — BeyondMimic's adaptive sampling over start times. The table is cut, in frame order, into
  `bins` groups of about equal size; each keeps a running failure rate of the episodes that started in
  it, and a start draws its group in proportion to that rate, mixed with a `uniform_share` of draws
  spread as uniform draws would be, so groups that are already solved are still rehearsed. Failures
  are charged to where an episode *started*, not where it fell: on the far jump the policy falls 0.9 s
  after a start at the touch-down (frames 84–107) and stands from every start 0.18 s later
  (benchmarks/RESULTS.md, commit 9018155), so the frames to practise are the ones it starts from.

Draws use torch's global generator (the trainer saves and restores it); the failure rates are part of
the env's `state_dict`.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import StartFrameSamplingConfig


def allowed_start_frames(mode: str, keyframes: np.ndarray, labels, num_frames: int) -> np.ndarray:
    """Frames a reference-state start may use (`EnvConfig.rsi_frames`): "keyframes" only, or "stance":
    every frame but those in the air (after a keyframe labelled takeoff, before the next labelled landing).
    Never the last frame, which would time out at once."""
    if mode == "keyframes":
        return keyframes[keyframes < num_frames - 1]
    allowed = np.ones(num_frames - 1, dtype=bool)
    labels = [str(label) for label in labels] if labels is not None else [""] * keyframes.size
    for i, label in enumerate(labels):
        if not label.startswith("takeoff"):
            continue
        landing = next((keyframes[j] for j in range(i + 1, keyframes.size) if labels[j].startswith("landing")),
                       num_frames)
        allowed[keyframes[i] + 1 : landing] = False  # the takeoff and the landing frames stay
    return np.flatnonzero(allowed)


class StartFrameSampler:
    def __init__(self, cfg: StartFrameSamplingConfig, frames: torch.Tensor, num_frames: int):
        self.cfg = cfg
        self.frames = frames
        self.device = frames.device
        count = frames.numel()
        self.num_bins = max(1, min(cfg.bins, count))
        # bin b holds table indices [bin_start[b], bin_start[b + 1]): equal counts, in frame order
        self.bin_start = torch.div(torch.arange(self.num_bins + 1, device=self.device) * count, self.num_bins,
                                   rounding_mode="floor")
        self.bin_size = (self.bin_start[1:] - self.bin_start[:-1]).to(torch.float64)
        self.bin_of_frame = torch.full((num_frames,), -1, dtype=torch.long, device=self.device)
        for b in range(self.num_bins):
            self.bin_of_frame[frames[self.bin_start[b]:self.bin_start[b + 1]]] = b
        # pessimistic start, as the ψ sampler's: every group is assumed to fail until episodes say otherwise
        self.failure_rate = torch.ones(self.num_bins, dtype=torch.float64, device=self.device)

    @property
    def adaptive(self) -> bool:
        return self.cfg.mode == "adaptive"

    def probabilities(self) -> torch.Tensor:
        """(bins,) the chance that a start falls in each group."""
        uniform = self.bin_size / self.bin_size.sum()
        if not self.adaptive:
            return uniform
        total = self.failure_rate.sum()
        by_failure = self.failure_rate / total if total > 0 else uniform
        share = self.cfg.uniform_share
        return share * uniform + (1.0 - share) * by_failure

    def draw(self, n: int) -> torch.Tensor:
        """(n,) start frames."""
        if not self.adaptive:
            return self.frames[torch.randint(self.frames.numel(), (n,), device=self.device)]
        bins = torch.multinomial(self.probabilities().to(torch.float32), n, replacement=True)
        within = (torch.rand(n, device=self.device, dtype=torch.float64) * self.bin_size[bins]).long()
        return self.frames[self.bin_start[bins] + within]

    def record(self, start_frames: torch.Tensor, failed: torch.Tensor) -> None:
        """Episodes that ended: the frame each started at and whether it failed. Episodes from t = 0 are
        ignored (they have their own share, 1 − rsi_prob, and would otherwise charge the first group
        with every fall of the whole clip), and so are starts outside the table."""
        if not self.adaptive or start_frames.numel() == 0:
            return
        bins = self.bin_of_frame[start_frames]
        keep = (bins >= 0) & (start_frames > 0)
        bins, failed = bins[keep], failed[keep].to(torch.float64)
        counts = torch.bincount(bins, minlength=self.num_bins).to(torch.float64)
        fails = torch.bincount(bins, weights=failed, minlength=self.num_bins)
        seen = counts > 0
        batch_rate = fails[seen] / counts[seen]
        alpha = self.cfg.rate_smoothing
        self.failure_rate[seen] = (1.0 - alpha) * self.failure_rate[seen] + alpha * batch_rate

    def state_dict(self) -> dict:
        return {"failure_rate": self.failure_rate.detach().cpu().clone()}

    def load_state_dict(self, state: dict) -> None:
        rate = state["failure_rate"]
        if rate.shape != self.failure_rate.shape:
            raise PipelineInputError("env state", "start_sampler.failure_rate",
                                     f"expected {tuple(self.failure_rate.shape)} groups, got {tuple(rate.shape)}")
        self.failure_rate = rate.to(self.device, torch.float64).clone()
