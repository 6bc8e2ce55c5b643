"""The mean of a policy's weights over the end of a run (`train.average_tail`).

Late in a stage the keyframe-error threshold relaxes and the policy keeps moving: on learn_cpu one run's
checkpoints ten iterations apart read 0.875-0.984 from t = 0, another's 0.828-0.969, so where a run stops
decides its result by a few episodes. The mean of the last few snapshots read about the median snapshot or a
little above it (0.95-0.98 and 0.875-0.89), not always above the last one (benchmarks/RESULTS.md, session
30): a steadier result, not a better one. Equal weights over snapshots taken every few iterations, as
stochastic weight averaging does; the observation normalisers are averaged with the layers, so the mean
policy sees inputs scaled as its layers were on average.
"""

from __future__ import annotations

import torch


class WeightAverage:
    """Running equal-weight mean of state dicts: floating-point tensors are averaged (in float64),
    anything else is taken from the latest one added."""

    def __init__(self) -> None:
        self.sums: dict[str, torch.Tensor] = {}
        self.latest: dict[str, torch.Tensor] = {}
        self.count = 0

    def add(self, state: dict[str, torch.Tensor]) -> None:
        if self.count and set(state) != set(self.latest):
            raise ValueError("WeightAverage.add: the state dict's keys differ from the ones averaged so far")
        for key, value in state.items():
            value = value.detach()
            self.latest[key] = value.clone()
            if value.is_floating_point():
                self.sums[key] = value.double().clone() if key not in self.sums else self.sums[key] + value.double()
        self.count += 1

    def mean(self) -> dict[str, torch.Tensor]:
        if not self.count:
            raise ValueError("WeightAverage.mean: nothing added yet")
        return {key: (self.sums[key] / self.count).to(value.dtype) if key in self.sums else value
                for key, value in self.latest.items()}

    def state_dict(self) -> dict:
        return {"sums": dict(self.sums), "latest": dict(self.latest), "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.sums, self.latest, self.count = dict(state["sums"]), dict(state["latest"]), int(state["count"])
