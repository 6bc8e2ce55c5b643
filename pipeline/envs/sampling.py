"""Which D_edit sample (ψ) a world tracks next: uniform, adaptive to where episodes fail, a
curriculum that widens ψ outwards from the clip's own value, or an even sweep for evaluation.

* adaptive — BeyondMimic's idea (there over start times of a long motion, here over the edited
  samples): keep a running failure rate per sample and draw in proportion to it, mixed with a uniform
  share so solved samples are still rehearsed.
* curriculum — legged_gym's terrain curriculum over edit size: the samples are ranked by |ψ − ψ_raw|
  and cut into `levels` groups; each world draws from its own level, goes one up after an episode it
  finishes and one down after a fall, and a world that finishes the top level restarts at a random
  one so the whole range stays rehearsed. With `split_sides` the samples short of ψ_raw and those
  beyond it have levels of their own and each world walks one side: pooled, a level's short gaps
  (which the policy mostly lands) move its worlds up while its far ones fail. Worlds then gather
  where the policy is just failing, which uniform draws over a wide range (most of it out of reach
  or already solved) rarely visit. Each level keeps a running success rate; with `demotion:
  relative` a fall only sends a world down where its level succeeds clearly less often than the
  bottom level does, so the falls every level shares (the randomisation's, the exploration's) do not
  hold the walk at the bottom.
* sweep — evaluation: world w's k-th episode tracks sample (w + k·worlds) mod samples, so the samples
  are scored equally often and two policies meet the same ψ values. Uniform draws leave the ψ mix to
  chance (and to when each policy's episodes end), which moved a score by ±4 points over 128 episodes.

Only episodes that began before the first edited keyframe say anything about ψ (a reference-state
start after the far jump's landing succeeds at any ψ), so the env records those alone.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.config import SamplingConfig


class SampleSampler:
    def __init__(self, cfg: SamplingConfig, psi: np.ndarray, psi_raw: float, num_worlds: int, device="cpu"):
        self.cfg = cfg
        self.num_samples = len(psi)
        self.device = torch.device(device)
        # adaptive: start pessimistic, every sample is assumed to fail until episodes say otherwise
        self.failure_rate = torch.ones(self.num_samples, dtype=torch.float64, device=device)
        # curriculum: level l owns samples level_table[l, :level_size[l]] (ranked by edit size); a dataset
        # with fewer samples than levels gets one level per sample
        # with `split_sides` the shorter and the farther side of ψ_raw get levels of their own (side 0's
        # first), and each world walks one side, as legged_gym's robots each walk one terrain type
        psi = np.asarray(psi, dtype=np.float64)
        offset = np.abs(psi - psi_raw)
        if cfg.split_sides:
            sides = [side for side in (np.flatnonzero(psi < psi_raw), np.flatnonzero(psi >= psi_raw)) if len(side)]
        else:
            sides = [np.arange(self.num_samples)]
        groups, level_side = [], []
        for side_index, side in enumerate(sides):
            ranked = side[np.argsort(offset[side], kind="stable")]
            side_groups = np.array_split(ranked, min(cfg.levels, len(side)))
            groups += side_groups
            level_side += [side_index] * len(side_groups)
        table = np.zeros((len(groups), max(len(g) for g in groups)), dtype=np.int64)
        for row, group in zip(table, groups):
            row[:len(group)] = group
        self.level_table = torch.as_tensor(table, device=device)
        self.level_side = level_side  # the side each level belongs to (0 throughout unless split)
        self.sample_level = torch.zeros(self.num_samples, dtype=torch.long, device=device)
        for index, group in enumerate(groups):
            self.sample_level[torch.as_tensor(group, device=device)] = index
        self.level_size = torch.as_tensor([len(g) for g in groups], device=device)
        # each world's side, its worlds in proportion to the side's samples; a world's walk is bounded
        # by its side's bottom and top level
        bounds = np.round(np.cumsum([len(side) for side in sides]) / self.num_samples * num_worlds)
        world_side = np.searchsorted(bounds, np.arange(num_worlds), side="right")
        first = np.searchsorted(level_side, np.arange(len(sides)))
        last = np.searchsorted(level_side, np.arange(len(sides)), side="right") - 1
        self.bottom_level = torch.as_tensor(first[world_side], device=device)
        self.top_level = torch.as_tensor(last[world_side], device=device)
        self.level = self.bottom_level.clone()
        self.rehearsing = torch.zeros(num_worlds, dtype=torch.bool, device=device)  # drawn by `uniform_share`
        # curriculum: each level's running success rate over the episodes recorded there (0 until measured),
        # a plain mean over its first 1/level_rate episodes (an EMA from 0 would read a new level as failing)
        self.level_success = torch.zeros(len(groups), dtype=torch.float64, device=device)
        self.level_episodes = torch.zeros(len(groups), dtype=torch.float64, device=device)
        self.num_worlds = num_worlds
        self.episodes_drawn = torch.zeros(num_worlds, dtype=torch.long, device=device)  # sweep: per world

    @property
    def num_levels(self) -> int:
        return self.level_table.shape[0]

    def probabilities(self) -> torch.Tensor:
        """Adaptive and uniform modes: the chance of each sample at the next draw."""
        uniform = torch.full_like(self.failure_rate, 1.0 / self.num_samples)
        if self.cfg.mode != "adaptive":
            return uniform
        total = float(self.failure_rate.sum())
        if total <= 0.0:
            return uniform
        u = self.cfg.uniform_ratio
        return u * uniform + (1.0 - u) * self.failure_rate / total

    def draw(self, worlds: torch.Tensor) -> torch.Tensor:
        """The sample index each of `worlds` tracks in its next episode."""
        n = worlds.numel()
        if self.cfg.mode == "uniform":
            return torch.randint(self.num_samples, (n,), device=self.device)
        if self.cfg.mode == "adaptive":
            return torch.multinomial(self.probabilities(), n, replacement=True)
        if self.cfg.mode == "sweep":
            sample = (worlds + self.num_worlds * self.episodes_drawn[worlds]) % self.num_samples
            self.episodes_drawn[worlds] += 1
            return sample
        level = self.level[worlds]
        slot = (torch.rand(n, device=self.device) * self.level_size[level]).long()
        drawn = self.level_table[level, slot]
        if self.cfg.uniform_share <= 0.0:  # no draws at all: the same random stream as before the option
            return drawn
        anywhere = torch.rand(n, device=self.device) < self.cfg.uniform_share
        self.rehearsing[worlds] = anywhere
        return torch.where(anywhere, torch.randint(self.num_samples, (n,), device=self.device), drawn)

    def record(self, worlds: torch.Tensor, samples: torch.Tensor, failed: torch.Tensor) -> None:
        """Episodes that tested the edit and ended this step: their world, sample and whether they failed."""
        if worlds.numel() == 0:
            return
        if self.cfg.mode == "adaptive":
            self.failure_rate = running_rate(self.failure_rate, samples, failed, self.cfg.rate)
        elif self.cfg.mode == "curriculum":
            # an episode counts towards its sample's level; one drawn uniformly does not move its world
            self.level_success = running_rate(self.level_success, self.sample_level[samples], ~failed,
                                              self.cfg.level_rate, self.level_episodes)
            walking = ~self.rehearsing[worlds]
            worlds, failed = worlds[walking], failed[walking]
            level, bottom, top = self.level[worlds], self.bottom_level[worlds], self.top_level[worlds]
            demoted = failed
            if self.cfg.demotion == "relative":
                demoted = failed & (self.level_success[level] <= self.cfg.relative_ratio * self.level_success[bottom])
            moved = torch.where(demoted, torch.maximum(level - 1, bottom),
                                torch.where(failed, level, torch.minimum(level + 1, top)))
            graduated = ~failed & (level == top)
            restart = bottom + (torch.rand(worlds.numel(), device=self.device) * (top - bottom + 1)).long()
            self.level[worlds] = torch.where(graduated, restart, moved)

    def mean_level(self) -> float:
        """Curriculum progress in [0, 1]: the worlds' mean height on their side's levels."""
        height = (self.level - self.bottom_level).double() / (self.top_level - self.bottom_level).clamp(min=1)
        return float(height.mean())

    _STATE = ("failure_rate", "level", "level_success", "level_episodes", "rehearsing", "episodes_drawn")

    def state_dict(self) -> dict:
        return {name: getattr(self, name).detach().cpu().clone() for name in self._STATE}

    def load_state_dict(self, state: dict) -> None:
        for name in self._STATE:
            if name not in state:  # states saved before the curriculum and the sweep existed
                continue
            saved, current = state[name], getattr(self, name)
            if saved.shape != current.shape:
                raise PipelineInputError("env state", f"sampler.{name}",
                                         f"expected {tuple(current.shape)}, got {tuple(saved.shape)}")
            setattr(self, name, saved.to(current.device, current.dtype).clone())


def running_rate(rate: torch.Tensor, index: torch.Tensor, outcome: torch.Tensor, step: float,
                 episodes: torch.Tensor | None = None) -> torch.Tensor:
    """`rate` (one entry per sample or level) after the episodes `index` ended with `outcome` (bool):
    one EMA step of size `step` per episode; several episodes of one entry in one call count together.
    With `episodes` (each entry's count so far, updated in place) an entry's first 1/step episodes are
    averaged plainly instead, so its rate does not start biased towards its initial value."""
    count = torch.zeros_like(rate).index_add_(0, index, torch.ones_like(index, dtype=rate.dtype))
    hits = torch.zeros_like(rate).index_add_(0, index, outcome.to(rate.dtype))
    weight = (step * count).clamp(max=1.0)
    if episodes is not None:
        episodes += count
        weight = torch.maximum(weight, count / episodes.clamp(min=1.0))
    return torch.where(count > 0, rate + weight * (hits / count.clamp(min=1) - rate), rate)
